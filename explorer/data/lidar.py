"""Simulating a 2D LiDAR from dense depth: one image row becomes the scan vector."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScanConfig:
    """``row`` None = the centre row. ``points`` None = one return per image column; otherwise that
    many returns spread evenly over the width (a coarser angular resolution). ``dropout`` is the
    probability that a return is lost, ``noise`` the std of range noise in metres."""

    row: int | None = None
    points: int | None = None
    max_range: float = 10.0
    dropout: float = 0.0
    noise: float = 0.0

    def row_for(self, height: int) -> int:
        return height // 2 if self.row is None else min(max(int(self.row), 0), height - 1)


def simulate_scan(depth: np.ndarray, config: ScanConfig = ScanConfig(),
                  rng: np.random.Generator | None = None) -> tuple[np.ndarray, int]:
    """(scan (W,) float32 metres, 0 = no return; its row) from a dense depth map (H, W)."""
    h, w = depth.shape
    row = config.row_for(h)
    scan = depth[row].astype(np.float32).copy()
    if config.points is not None and config.points < w:
        keep = np.zeros(w, dtype=bool)
        keep[np.round(np.linspace(0, w - 1, max(int(config.points), 1))).astype(int)] = True
        scan[~keep] = 0.0
    if rng is None:
        rng = np.random.default_rng(0)
    if config.noise > 0:
        scan = np.where(scan > 0, scan + rng.normal(0, config.noise, w).astype(np.float32), 0.0)
    if config.dropout > 0:
        scan[rng.random(w) < config.dropout] = 0.0
    scan[(scan > config.max_range) | (scan < 0)] = 0.0
    return scan.astype(np.float32), row


def scan_from_image(scan_image: np.ndarray) -> tuple[np.ndarray, int]:
    """Collapse a sparse image of one scan's returns to (scan vector, its median row)."""
    mask = scan_image > 0
    if not mask.any():
        return np.zeros(scan_image.shape[1], np.float32), scan_image.shape[0] // 2
    rows = np.nonzero(mask)[0]
    row = int(np.median(rows))
    dist = np.where(mask, np.abs(np.arange(scan_image.shape[0])[:, None] - row), 10 ** 9)
    pick = dist.argmin(axis=0)
    scan = scan_image[pick, np.arange(scan_image.shape[1])].astype(np.float32)
    scan[~mask.any(axis=0)] = 0.0
    return scan, row
