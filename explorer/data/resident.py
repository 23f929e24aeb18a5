"""Training batches for an accelerator that must not wait on the CPU.

A training set whose augmentation is a flip alone (``FLIP_ONLY_KINDS``: the synthetic scenes, KITTI)
and that fits a memory budget is held whole on the device, at the network's input size: images as
uint8, depth as float16 where that is exact. A batch is then drawn by index there, mirrored there and
its scan read off its depth there: no per-item Python, no collation, no host-to-device copy per step.
The batches are the very ones a ``DataLoader(shuffle=True, generator=..., drop_last=True)`` over the
data set gives (same order, same flips, same values), so training does not change with where the data
lives. Any other set goes through a ``DataLoader`` with worker processes and pinned memory on CUDA.
"""

from __future__ import annotations

import os
from typing import Callable, Iterator

import numpy as np
import torch
from torch.utils.data import DataLoader

from explorer.data import FLIP_ONLY_KINDS, DepthDataset

#: the share of the GPU's free memory a resident training set may take (the rest is the network's)
CUDA_SHARE = 0.25
#: the most a resident set may take in host memory when training on the CPU
CPU_BUDGET_BYTES = 2 << 30


def resident_bytes(dataset) -> int | None:
    """What ``dataset`` takes held on a device (float32 depth, the most it takes), or None where it
    cannot be held so: augmented beyond a flip, or a scan drawn with noise or dropout per item."""
    if not isinstance(dataset, DepthDataset) or dataset.kind not in FLIP_ONLY_KINDS:
        return None
    if dataset.scan.noise or dataset.scan.dropout or dataset.lidar is not None:
        return None
    h, w = dataset.input_size
    return len(dataset) * (h * w * (3 + 4) + w * 4)


def memory_budget(device: torch.device) -> int:
    """The bytes a resident set may take on ``device``."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free * CUDA_SHARE)
    return CPU_BUDGET_BYTES


class ResidentSet:
    """A flip-only data set's frames at the input size, held on ``device``."""

    def __init__(self, dataset: DepthDataset, device: torch.device,
                 progress: Callable[[int, int], None] | None = None) -> None:
        n, (h, w) = len(dataset), dataset.input_size
        rgb = np.empty((n, h, w, 3), np.uint8)
        depth = np.empty((n, h, w), np.float32)
        scans, rows = np.zeros((n, w), np.float32), np.full(n, dataset.scan.row_for(h), np.int64)
        column_rows = np.repeat(rows[:, None], w, axis=1)
        measured = False
        for i in range(n):
            rgb[i], depth[i], scan, row, per_column = dataset.unflipped(i)
            if scan is not None:
                scans[i], rows[i], column_rows[i], measured = scan, row, per_column, True
            if progress:
                progress(i + 1, n)
        half = depth.astype(np.float16)
        exact = np.array_equal(half.astype(np.float32), depth)
        self.dataset, self.device = dataset, device
        self.images = torch.from_numpy(rgb).to(device)
        self.depths = torch.from_numpy(half if exact else depth).to(device)
        self.scans = torch.from_numpy(scans).to(device) if measured else None
        self.rows = torch.from_numpy(rows)               # on the host: the network takes the row as an int
        self.column_rows = torch.from_numpy(column_rows).to(device)
        self.keep = torch.from_numpy(_scan_mask(dataset.scan.points, w)).to(device)

    def __len__(self) -> int:
        return len(self.images)

    def batch(self, index: torch.Tensor, flips: torch.Tensor, host_index: torch.Tensor) -> dict:
        """Items ``index`` (on the device) as one batch, item i mirrored where ``flips[i]``; the same
        dict of tensors that collating ``DepthDataset`` items gives."""
        flip = flips[index]
        rgb = self.images[index]
        rgb = torch.where(flip[:, None, None, None], rgb.flip(2), rgb)
        depth = self.depths[index].float()
        depth = torch.where(flip[:, None, None], depth.flip(2), depth)
        rows = self.rows[host_index]
        column_rows = self.column_rows[index]
        column_rows = torch.where(flip[:, None], column_rows.flip(1), column_rows)
        if self.scans is not None:
            scan = self.scans[index]
            scan = torch.where(flip[:, None], scan.flip(1), scan)
        else:   # as simulate_scan: the row of the (mirrored) depth, returns kept, out of range dropped
            scan = depth[:, self.dataset.scan.row_for(depth.shape[1]), :]
            scan = torch.where(self.keep, scan, torch.zeros_like(scan))
            scan = torch.where((scan > self.dataset.scan.max_range) | (scan < 0), torch.zeros_like(scan), scan)
        # (B, H, W, 3) permuted is (B, 3, H, W) in channels-last order, the layout the network trains in
        return {"image": rgb.permute(0, 3, 1, 2).float() / 255.0, "depth": depth[:, None],
                "scan": scan, "scan_rows": column_rows, "scan_row": rows}


def _scan_mask(points: int | None, w: int) -> np.ndarray:
    """The columns a scan of ``points`` returns keeps (as ``simulate_scan`` spreads them)."""
    keep = np.ones(w, dtype=bool)
    if points is not None and points < w:
        keep[:] = False
        keep[np.round(np.linspace(0, w - 1, max(int(points), 1))).astype(int)] = True
    return keep


class ResidentLoader:
    """Batches of a :class:`ResidentSet` in the order ``DataLoader(dataset, batch_size, shuffle=True,
    generator=generator, drop_last=True)`` draws them (it draws the order, over indices): one epoch per
    iteration, reading the data set's ``epoch`` for the flips."""

    def __init__(self, resident: ResidentSet, batch_size: int, generator: torch.Generator) -> None:
        self.resident = resident
        self.order = DataLoader(range(len(resident)), batch_size=batch_size, shuffle=True, generator=generator,
                                drop_last=True)

    def __len__(self) -> int:
        return len(self.order)

    def __iter__(self) -> Iterator[dict]:
        host = list(self.order)
        if not host:
            return
        device = self.resident.device
        on_device = torch.stack(host).to(device)      # one copy per epoch, none per step
        ds = self.resident.dataset
        flips = torch.tensor([ds.flipped(i) for i in range(len(ds))], dtype=torch.bool).to(device)
        for k, index in enumerate(host):
            yield self.resident.batch(on_device[k], flips, index)


def training_batches(dataset, batch_size: int, generator: torch.Generator, device: torch.device,
                     budget: int | None = None, progress: Callable[[int, int], None] | None = None):
    """Shuffled batches of ``dataset`` for training on ``device`` (an iterable with a length, one epoch
    per iteration, ``generator`` seeding each epoch's order): held on the device where
    :func:`resident_bytes` fits ``budget`` (default :func:`memory_budget`), else a ``DataLoader``: on
    CUDA with worker processes and pinned memory, so that the next batches are prepared while the GPU
    runs. ``progress(done, total)`` follows the frames being placed on the device."""
    need = resident_bytes(dataset)
    if need is not None and len(dataset) >= batch_size and need <= (memory_budget(device) if budget is None else budget):
        return ResidentLoader(ResidentSet(dataset, device, progress), batch_size, generator)
    workers = loader_workers() if device.type == "cuda" else 0
    return DataLoader(dataset, batch_size=batch_size, shuffle=True, generator=generator, drop_last=True,
                      num_workers=workers, pin_memory=device.type == "cuda", prefetch_factor=4 if workers else None)


def loader_workers() -> int:
    """Worker processes for one training process: this machine's cores shared among torchrun's local
    processes, one core left for the process feeding the GPU, at most 8."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    local = max(int(os.environ.get("LOCAL_WORLD_SIZE", "1")), 1)
    return max(0, min(8, cores // local - 1))
