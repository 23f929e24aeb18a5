"""The camera's motion from the 2D LiDAR's own scans: what scores paths on a recording without depth."""

import numpy as np

from explorer.data.odometry import camera_motion, match_scans
from explorer.scan import LaserScan, mount_transform

#: an L-shaped room with a pillar (metres, in the LiDAR's plane): walls that pin down every motion
ROOM = [((-2, -3), (6, -3)), ((6, -3), (6, 1)), ((6, 1), (3, 1)), ((3, 1), (3, 4)), ((3, 4), (-2, 4)),
        ((-2, 4), (-2, -3)), ((1.5, -1), (2, -1)), ((2, -1), (2, -0.5)), ((2, -0.5), (1.5, -0.5)),
        ((1.5, -0.5), (1.5, -1))]


def sweep(x: float, y: float, yaw: float, noise: float = 0.0, seed: int = 0) -> LaserScan:
    """A 360-degree, 0.5-degree sweep of ROOM from a LiDAR at (x, y) facing ``yaw``."""
    angles = np.radians(np.arange(-180, 180, 0.5))
    dx, dy = np.cos(angles + yaw), np.sin(angles + yaw)
    ranges = np.full(len(angles), np.inf)
    for (ax, ay), (bx, by) in ROOM:   # where each ray meets each wall: x + t d = a + s (b - a)
        ex, ey = bx - ax, by - ay
        det = -dx * ey + dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-(ax - x) * ey + (ay - y) * ex) / det
            s = (dx * (ay - y) - dy * (ax - x)) / det
        hit = (np.abs(det) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        ranges = np.where(hit, np.minimum(ranges, t), ranges)
    ranges = ranges + np.random.default_rng(seed).normal(0, noise, len(ranges))
    return LaserScan(float(angles[0]), float(np.radians(0.5)), 0.1, 20.0, ranges.astype(np.float32))


def test_scan_matching_recovers_a_turn_and_a_shift():
    x, y, yaw = 0.12, -0.05, np.radians(4.0)
    motion = match_scans(sweep(0, 0, 0, noise=0.01, seed=1), sweep(x, y, yaw, noise=0.01, seed=2))
    # a static point p of the first sweep's frame lies at motion @ p in the second's
    expected = np.linalg.inv(np.array([[np.cos(yaw), -np.sin(yaw), 0, x], [np.sin(yaw), np.cos(yaw), 0, y],
                                       [0, 0, 1, 0], [0, 0, 0, 1]]))
    assert motion is not None
    assert np.allclose(motion[:2, 3], expected[:2, 3], atol=0.01)
    assert np.degrees(abs(np.arctan2(motion[1, 0], motion[0, 0]) - np.arctan2(expected[1, 0], expected[0, 0]))) < 0.3


def test_sweeps_that_do_not_pin_the_motion_down_give_none():
    few = sweep(0, 0, 0)
    ranges = np.full(len(few.ranges), np.inf, np.float32)
    ranges[:10] = few.ranges[:10]
    blind = LaserScan(few.angle_min, few.angle_increment, few.range_min, few.range_max, ranges)
    assert match_scans(blind, few) is None
    # a different room altogether: too few returns line up with it
    elsewhere = LaserScan(few.angle_min, few.angle_increment, 0.1, 20.0, np.asarray(few.ranges)[::-1] * 1.7)
    assert match_scans(few, elsewhere) is None


def test_the_mount_carries_the_lidars_motion_into_the_cameras_frame():
    mount = mount_transform(height=0.1, forward=0.05)
    step = 0.1   # the robot drives 10 cm along the LiDAR's x axis, the camera's optical axis
    motion = camera_motion(sweep(0, 0, 0), sweep(step, 0, 0), mount)
    assert motion is not None
    # a point ahead of the camera comes 10 cm nearer
    assert np.allclose(motion[:3, 3], [0, 0, -step], atol=0.01)
    assert np.allclose(motion[:3, :3], np.eye(3), atol=1e-3)
