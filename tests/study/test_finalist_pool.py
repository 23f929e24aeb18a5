"""Which device each finalist worker trains on."""

import torch

import explorer.study._finalist_pool as pool


def test_one_gpu_retrains_one_finalist_at_a_time_on_its_index(monkeypatch):
    # worker processes would spend longer starting than sharing the GPU gains; a device without an
    # index would be refused by torch.cuda.set_device
    monkeypatch.setattr(pool, "resolve_accelerator", lambda accelerator: torch.device("cuda"))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    assert pool.finalist_devices("cuda", 2) == ["cuda:0"]


def test_several_gpus_take_one_worker_each_whatever_workers_says(monkeypatch):
    monkeypatch.setattr(pool, "resolve_accelerator", lambda accelerator: torch.device("cuda"))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 3)
    assert pool.finalist_devices("cuda", 1) == ["cuda:0", "cuda:1", "cuda:2"]


def test_cpu_workers(monkeypatch):
    assert pool.finalist_devices("cpu", 2) == ["cpu", "cpu"]
