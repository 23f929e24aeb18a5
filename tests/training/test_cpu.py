"""PyTorch's CPU threads: the cores other work leaves free."""

import multiprocessing as mp
import time

import pytest
import torch

from explorer.training import cpu


def _spin() -> None:
    while True:
        pass


@pytest.mark.parametrize("cores, busy, threads", [(2, 0.0, 2), (2, 0.3, 2), (2, 0.7, 1), (2, 1.0, 1), (2, 2.6, 1),
                                                  (16, 3.4, 13), (16, 0.5, 16)])
def test_a_core_counts_as_taken_from_six_tenths_of_it(cores, busy, threads):
    assert cpu.free_threads(cores, busy) == threads


def test_a_busy_process_beside_is_seen():
    spinner = mp.get_context("fork").Process(target=_spin, daemon=True)
    spinner.start()
    try:
        time.sleep(0.3)
        busy = cpu.busy_elsewhere(0.5)
    finally:
        spinner.terminate()
    assert busy is not None and busy >= 0.6     # one core spinning (more if the machine is busy anyway)


def test_without_proc_stat_nothing_changes(monkeypatch, tmp_path):
    monkeypatch.setattr(cpu, "PROC_STAT", tmp_path / "absent")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    assert cpu.use_free_cores() == (before, None) and torch.get_num_threads() == before


def test_threads_the_user_set_are_left_alone(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setattr(cpu, "busy_elsewhere", lambda *a: pytest.fail("measured although the user chose"))
    assert cpu.use_free_cores()[1] is None


def test_threads_never_exceed_pytorchs_default(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    monkeypatch.setattr(cpu, "busy_elsewhere", lambda *a: 0.0)
    monkeypatch.setattr(cpu, "usable_cores", lambda: list(range(64)))
    before = torch.get_num_threads()
    try:
        assert cpu.use_free_cores() == (before, 0.0)
    finally:
        torch.set_num_threads(before)
