"""The camera's motion between frames from the 2D LiDAR's own scans (scan matching).

A recording without depth is scored by how well each path's depth map warps the neighbouring frames
onto the target (:func:`explorer.training.selfsup.photometric_score`). That needs the relative poses of
the validation frames, and they must not come from the network being scored: every candidate is
judged against the same motion. A 2D LiDAR measures that motion in its plane, metric and independent
of the camera: point-to-point ICP aligns one sweep onto the next, and the mount ``T_cam_lidar`` carries
the motion into the camera's frame. A pair whose sweeps do not pin the motion down (too few returns
matched, a poor fit, or walls of one direction only) has no pose and is left out of the score.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from explorer.scan import LaserScan

#: ICP's correspondence gate shrinks from the first value to the last over the iterations (metres)
GATES = (0.5, 0.2, 0.1, 0.05)
ITERATIONS_PER_GATE = 8
#: a match is trusted when this share of the source's returns lie within the last gate after alignment
MIN_INLIERS = 0.6
MIN_RETURNS = 20
NORMAL_NEIGHBOURS = 5
#: the least share of the returns' normals across the main wall direction for a shift along it to be seen
MIN_NORMAL_SPREAD = 0.02


def scan_points_xy(scan: LaserScan) -> np.ndarray:
    """The valid returns of ``scan`` as (N, 2) points in the LiDAR's plane (x forward, y left)."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    a = scan.angles
    valid = np.isfinite(r) & (r >= scan.range_min) & (r <= scan.range_max) & (r > 0)
    return np.stack([r[valid] * np.cos(a[valid]), r[valid] * np.sin(a[valid])], axis=1)


def _normals(points: np.ndarray, tree: cKDTree) -> np.ndarray:
    """Unit normals (N, 2) of the surfaces the points lie on: the least-spread direction of each point's
    nearest returns."""
    _, idx = tree.query(points, k=min(NORMAL_NEIGHBOURS, len(points)))
    local = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return vectors[:, :, 0]


def _point_to_line_step(src: np.ndarray, dst: np.ndarray, normals: np.ndarray) -> tuple[float, np.ndarray]:
    """The small turn and shift that minimise the squared distances of ``src`` to the lines through
    ``dst`` with ``normals`` (linearised in the angle): sweeps along a wall slide freely, which pulls a
    point-to-point match short of the real motion."""
    lever = normals[:, 1] * src[:, 0] - normals[:, 0] * src[:, 1]
    a = np.stack([lever, normals[:, 0], normals[:, 1]], axis=1)
    b = np.einsum("ni,ni->n", normals, dst - src)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    return float(x[0]), x[1:]


def match_scans(source: LaserScan, target: LaserScan) -> np.ndarray | None:
    """The LiDAR's motion as a 4x4 rigid transform M (a turn about its z axis and a shift in its
    plane) with ``M @ p`` in the target sweep's frame for a static point ``p`` of the source sweep's;
    None where the sweeps do not determine it. Point-to-line ICP from no motion."""
    src, dst = scan_points_xy(source), scan_points_xy(target)
    if len(src) < MIN_RETURNS or len(dst) < MIN_RETURNS:
        return None
    tree = cKDTree(dst)
    normals = _normals(dst, tree)
    angle, shift = 0.0, np.zeros(2)
    for gate in GATES:
        for _ in range(ITERATIONS_PER_GATE):
            moved = src @ _rotation(angle).T + shift
            dist, idx = tree.query(moved, distance_upper_bound=gate)
            near = np.isfinite(dist)
            if near.sum() < MIN_RETURNS:
                return None
            turn, step = _point_to_line_step(moved[near], dst[idx[near]], normals[idx[near]])
            angle, shift = angle + turn, _rotation(turn) @ shift + step
    moved = src @ _rotation(angle).T + shift
    dist, idx = tree.query(moved, distance_upper_bound=GATES[-1])
    near = np.isfinite(dist)
    if near.mean() < MIN_INLIERS or _degenerate(moved[near], normals[idx[near]]):
        return None
    motion = np.eye(4)
    motion[:2, :2], motion[:2, 3] = _rotation(angle), shift
    return motion


def _degenerate(points: np.ndarray, normals: np.ndarray) -> bool:
    """Whether the matched returns leave a motion free: walls of one direction only (a long straight
    wall or corridor lets the sweep slide along it)."""
    spread = np.linalg.eigvalsh(normals.T @ normals)   # how the walls' normals spread over the plane
    return bool(spread[0] < MIN_NORMAL_SPREAD * len(points))


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def camera_motion(source: LaserScan, target: LaserScan, T_cam_lidar: np.ndarray) -> np.ndarray | None:
    """The transform from the source frame's camera coordinates to the target frame's (4x4), from the
    LiDAR's motion between the two sweeps and the mount; None where the sweeps do not determine it."""
    motion = match_scans(source, target)
    if motion is None:
        return None
    return T_cam_lidar @ motion @ np.linalg.inv(T_cam_lidar)
