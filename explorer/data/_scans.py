"""The scan of one frame at the network's input size, whichever way the data gives it."""

from __future__ import annotations

import numpy as np

from explorer.data.lidar import ScanConfig, scan_from_image, simulate_scan
from explorer.scan import LidarModel, ScanPoints, column_scan, simulate_scan_points


def frame_scan(depth: np.ndarray, *, points: ScanPoints | None = None, scan_image: np.ndarray | None = None,
               lidar: LidarModel | None = None, K: np.ndarray | None = None, config: ScanConfig = ScanConfig(),
               rng: np.random.Generator | None = None, flipped: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """(scan (W,) metres, rows (W,), row) for a frame whose depth map at the input size is ``depth``:
    from a real scan's ``points`` (already at the input size) or sparse ``scan_image``; else simulated
    by ``lidar`` through ``K`` (the input size's intrinsics) on the frame as the camera saw it
    (``flipped``: the depth was mirrored after, so the scan is too); else the ideal row of ``config``."""
    h, w = depth.shape
    if points is not None:
        return column_scan(points, (h, w))
    if scan_image is not None:
        scan, row = scan_from_image(np.ascontiguousarray(scan_image))
        return scan, _rows_of_image(scan_image, row), row
    if lidar is not None:
        seen = depth[:, ::-1] if flipped else depth
        pts = simulate_scan_points(np.ascontiguousarray(seen), K, lidar, rng)
        if flipped:
            pts = ScanPoints(w - 1 - pts.u, pts.v, pts.z)
        return column_scan(pts, (h, w))
    scan, row = simulate_scan(depth, config, rng if (config.noise or config.dropout) else None)
    return scan, np.full(w, row, np.int64), row


def _rows_of_image(scan_image: np.ndarray, row: int) -> np.ndarray:
    """Per column the row of the return ``scan_from_image`` keeps (nearest ``row``), interpolated
    across columns without one."""
    mask = scan_image > 0
    h, w = scan_image.shape
    if not mask.any():
        return np.full(w, row, np.int64)
    dist = np.where(mask, np.abs(np.arange(h)[:, None] - row), 10 ** 9)
    pick = dist.argmin(axis=0)
    have = mask.any(axis=0)
    return np.round(np.interp(np.arange(w), np.nonzero(have)[0], pick[have])).astype(np.int64)
