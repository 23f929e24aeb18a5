"""Depth hints for self-supervised training (Watson et al., "Self-Supervised Monocular Depth Hints",
ICCV 2019), with multi-view photometric optimisation and the scan in place of stereo matching.

Why: on the synthetic sequences at training resolution, the photometric loss's own minimum is far
from the true depth at MonoDepth2's smoothness weight, and a network trained a few hundred steps on
it does not even reach path 0.
Optimising one free depth per pixel on the same loss, from path 0, with the data's poses and a
stronger smoothness, lands much closer to the truth. That map is a hint: each exit is pulled toward
it (``log(1 + |depth - hint|)``) at the pixels where the hint explains the neighbouring frames better
than the exit's own depth does, and left to the photometric loss elsewhere.

Hints need known camera motion (``--poses given``): they are computed once per training frame,
before training, and cached on disk under a key of the frames and the hint recipe.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable

import torch
from torch.utils.data import DataLoader, Dataset

from explorer.data.synthetic import cache_dir
from explorer.errors import refused_write
from explorer.files import writing_atomically
from explorer.model.exits import interpolate_scan
from explorer.training.selfsup import (
    MIN_DEPTH,
    SCAN_WEIGHT,
    reprojection_loss,
    scan_l1,
    smoothness,
    warp,
)

#: Adam steps on the free depth map, its step (metres) and its smoothness weight: where the optimisation
#: of 48 validation frames at 64x64 stops improving (RMSE 0.348 -> 0.25 m at 150 steps, 0.22 m at 400).
STEPS = 200
LR = 0.05
SMOOTHNESS = 0.1
BATCH = 16


def compute_hints(batch: dict, steps: int = STEPS, smoothness_weight: float = SMOOTHNESS, lr: float = LR,
                  start: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 1, H, W) depth hints for a batch of sequence samples with known poses: ``start`` (default
    path 0) refined by ``steps`` Adam steps on the photometric loss, the smoothness and the scan term."""
    image, K, scan = batch["image"], batch["K"], batch["scan"]
    row = int(torch.as_tensor(batch["scan_row"]).float().median())
    sources = [batch["sources"][:, k] for k in range(2)]
    poses = [batch["pose"][:, k] for k in range(2)]
    if start is None:
        start = interpolate_scan(scan, image.shape[2])
    depth = start.contiguous().clone().clamp(min=MIN_DEPTH)
    depth.requires_grad_(True)
    opt = torch.optim.Adam([depth], lr=lr)
    with torch.enable_grad():
        for _ in range(steps):
            d = depth.clamp(min=MIN_DEPTH)
            warped = [warp(s, d, K, p) for s, p in zip(sources, poses)]
            loss = reprojection_loss(image, sources, warped)[0].mean() + smoothness_weight * smoothness(d, image) \
                + SCAN_WEIGHT * scan_l1(d, scan, row)
            opt.zero_grad()
            loss.backward()
            opt.step()
    return depth.detach().clamp(min=MIN_DEPTH)


def _fingerprint(dataset, steps: int) -> str:
    """Key of the frames and the recipe: the data set's size, input size and three of its samples."""
    h = hashlib.sha1(f"hints-v1-{len(dataset)}-{steps}-{LR}-{SMOOTHNESS}-{SCAN_WEIGHT}".encode())
    for i in sorted({0, len(dataset) // 2, len(dataset) - 1}):
        item = dataset[i]
        for key in ("image", "sources", "pose", "K", "scan"):
            h.update(torch.as_tensor(item[key]).numpy().tobytes())
    return h.hexdigest()[:12]


class HintedDataset(Dataset):
    """A sequence data set whose items carry ``hint`` (1, H, W); other attributes pass through."""

    def __init__(self, dataset, hints: torch.Tensor) -> None:
        self.dataset, self.hints = dataset, hints

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict:
        return {**self.dataset[i], "hint": self.hints[i]}

    def resized(self, input_size: tuple[int, int]) -> "HintedDataset":
        """The same samples at another input size, with hints computed there (once, then cached)."""
        return with_hints(self.dataset.resized(input_size))

    def __getattr__(self, name: str):
        if name in ("dataset", "hints"):  # not yet set (unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __setattr__(self, name: str, value) -> None:
        if name in ("dataset", "hints"):
            object.__setattr__(self, name, value)
        else:  # the training loop sets ``epoch`` on the data set it gets
            setattr(self.dataset, name, value)


def with_hints(dataset, steps: int = STEPS, cache: Path | None = None,
               progress: Callable[[int, int], None] | None = None) -> HintedDataset:
    """``dataset`` with a depth hint for every item, computed once (in order, ``BATCH`` at a time) and
    cached; an interrupted computation starts again, never leaving half a file."""
    path = (cache or cache_dir()) / f"hints-{_fingerprint(dataset, steps)}.pt"
    if path.is_file():
        try:   # tensors only: a cache file is never code
            cached = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:   # a damaged cache entry (disk full, foreign file): computed again below
            cached = None
        if isinstance(cached, torch.Tensor) and len(cached) == len(dataset):
            return HintedDataset(dataset, cached)
    hints = []
    for batch in DataLoader(dataset, batch_size=BATCH, shuffle=False):
        hints.append(compute_hints(batch, steps))
        if progress:
            progress(sum(len(h) for h in hints), len(dataset))
    stacked = torch.cat(hints)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with writing_atomically(path) as f:
            torch.save(stacked, f)
    except Exception as exc:   # a full or read-only cache: the hints serve this run, and are computed again
        if refused_write(exc) is None:
            raise
    return HintedDataset(dataset, stacked)
