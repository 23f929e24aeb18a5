"""A training set held on the device gives the batches a DataLoader over it gives, value for value."""

import pytest
import torch
from torch.utils.data import DataLoader

from conftest import TINY_DATA
from explorer.data import DepthDataset, ScanConfig, open_dataset
from explorer.data.resident import ResidentLoader, ResidentSet, resident_bytes, training_batches


def _epochs(loader, dataset, generator, epochs=2):
    out = []
    for epoch in range(epochs):
        dataset.epoch = epoch
        generator.manual_seed(epoch)
        out.append(list(loader))
    return out


def _same_batches(dataset, batch_size=4):
    gen = torch.Generator()
    plain = _epochs(DataLoader(dataset, batch_size=batch_size, shuffle=True, generator=gen, drop_last=True),
                    dataset, gen)
    resident = _epochs(ResidentLoader(ResidentSet(dataset, torch.device("cpu")), batch_size, gen), dataset, gen)
    assert [len(e) for e in plain] == [len(e) for e in resident] == [len(dataset) // batch_size] * 2
    flipped = 0
    for a_epoch, b_epoch in zip(plain, resident):
        for a, b in zip(a_epoch, b_epoch):
            assert set(a) == set(b)
            for key in a:
                assert a[key].shape == b[key].shape and torch.equal(a[key], b[key]), key
            flipped += int(not torch.equal(a["image"], a["image"].flip(3)))
    assert flipped   # the set's flips were exercised (and matched)


@pytest.mark.parametrize("scan", [ScanConfig(), ScanConfig(points=20, max_range=4.0, row=5)])
def test_resident_batches_are_the_data_loaders(scan):
    _same_batches(open_dataset(TINY_DATA, "train", (32, 48), scan=scan, seed=3))


def test_measured_scans_are_flipped_with_their_frames(shared_data):
    _same_batches(open_dataset(f"kitti:{shared_data / 'kitti-mini'}", "train", (64, 256)), batch_size=1)


def test_what_cannot_be_held_goes_through_a_data_loader():
    noisy = open_dataset(TINY_DATA, "train", (32, 32), scan=ScanConfig(noise=0.1))
    assert resident_bytes(noisy) is None                       # the noise is drawn per item
    nyu = DepthDataset([], "nyu", (32, 32), train=True)
    assert resident_bytes(nyu) is None                         # scaled, rotated, jittered per item
    cpu, gen = torch.device("cpu"), torch.Generator()
    clean = open_dataset(TINY_DATA, "train", (32, 32))
    assert isinstance(training_batches(clean, 4, gen, cpu), ResidentLoader)
    assert isinstance(training_batches(clean, 4, gen, cpu, budget=resident_bytes(clean) - 1), DataLoader)
    assert isinstance(training_batches(noisy, 4, gen, cpu), DataLoader)
    assert len(training_batches(clean, len(clean) + 1, gen, cpu)) == 0


def test_loader_workers_share_the_cores_among_local_processes(monkeypatch):
    from explorer.data import resident
    monkeypatch.setattr(resident.os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert resident.loader_workers() == 7
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")
    assert resident.loader_workers() == 8
    monkeypatch.setattr(resident.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert resident.loader_workers() == 0
