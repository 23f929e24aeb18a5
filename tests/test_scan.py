"""A 2D LiDAR's scan projected into the image, and simulated from depth the same way backwards."""

import math

import numpy as np
import pytest

from explorer.errors import UserError
from explorer.scan import (
    LaserScan,
    LidarModel,
    column_scan,
    lidar_model,
    mount_transform,
    project_scan,
    read_lidar_yaml,
    read_ranges,
    rigid_transform,
    simulate_ranges,
    simulate_scan_points,
)

K = np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]])   # a 128x96 image, centre (63.5, 47.5)
SHAPE = (96, 128)


def _wall_scan(z: float, model: LidarModel) -> LaserScan:
    """Ranges of a level LiDAR at the optical centre facing a wall ``z`` metres ahead."""
    return model.scan(z / np.cos(model.angle_min + model.angle_increment * np.arange(model.beams)))


def test_a_level_mount_at_the_optical_centre_lands_on_the_centre_row_at_the_wall_depth():
    model = lidar_model({"fov": 90, "resolution": 0.25}, "test")
    pts = project_scan(_wall_scan(3.0, model), model.transform, K, SHAPE)
    assert np.allclose(pts.z, 3.0) and np.allclose(pts.v, 47.5)
    # beam angle a (to the left) lands at u = cx - fx tan(a)
    scan, rows, row = column_scan(pts, SHAPE)
    assert np.allclose(scan[scan > 0], 3.0) and (scan > 0).mean() > 0.95 and row in (47, 48)


@pytest.mark.parametrize("tilt, sign", [(5.0, 1), (-5.0, -1)])
def test_a_plane_tilted_down_lands_below_the_centre_and_up_above(tilt, sign):
    model = lidar_model({"fov": 60, "resolution": 0.5, "tilt": tilt}, "test")
    depth = np.full(SHAPE, 3.0)
    pts = simulate_scan_points(depth, K, model)
    # on a wall 3 m ahead the plane is fx * tan(tilt) rows from the centre, and the returns read the wall
    assert np.allclose(pts.v - 47.5, sign * 100 * math.tan(math.radians(abs(tilt))), atol=0.6)
    assert np.allclose(pts.z, 3.0, atol=0.03)


def test_a_rolled_mount_projects_onto_a_slanted_line():
    model = lidar_model({"fov": 60, "resolution": 0.25, "roll": 10}, "test")
    scan, rows, _ = column_scan(simulate_scan_points(np.full(SHAPE, 2.0), K, model), SHAPE)
    slope = np.polyfit(np.nonzero(scan > 0)[0], rows[scan > 0], 1)[0]
    assert slope == pytest.approx(math.tan(math.radians(10)), abs=0.02)   # clockwise: the right side lower


def test_a_mount_above_the_camera_sees_near_returns_higher():
    model = lidar_model({"fov": 40, "height": 0.1}, "test")
    near = project_scan(_wall_scan(1.0, model), model.transform, K, SHAPE)
    far = project_scan(_wall_scan(4.0, model), model.transform, K, SHAPE)
    assert near.v.mean() == pytest.approx(47.5 - 100 * 0.1 / 1.0, abs=0.5)
    assert far.v.mean() == pytest.approx(47.5 - 100 * 0.1 / 4.0, abs=0.5)


def test_simulated_ranges_are_the_scene_plus_the_models_noise_and_dropouts():
    model = lidar_model({"fov": 60, "resolution": 0.5, "noise": 0.02, "dropout": 0.1}, "test")
    clean = simulate_ranges(np.full(SHAPE, 3.0), K, lidar_model({"fov": 60, "resolution": 0.5}, "test"))
    noisy = simulate_ranges(np.full(SHAPE, 3.0), K, model, np.random.default_rng(0))
    hit = np.isfinite(clean.ranges)
    assert hit.mean() > 0.95
    lost = hit & ~np.isfinite(noisy.ranges)
    assert 0.03 < lost.mean() < 0.2
    both = hit & np.isfinite(noisy.ranges)
    assert np.std(noisy.ranges[both] - clean.ranges[both]) == pytest.approx(0.02, rel=0.3)


def test_returns_out_of_range_behind_the_camera_or_outside_the_image_are_dropped():
    model = lidar_model({"fov": 359, "resolution": 1.0, "range_max": 5.0}, "test")
    ranges = np.full(model.beams, 3.0)
    ranges[model.beams // 2] = 6.0            # straight ahead, beyond range_max
    pts = project_scan(model.scan(ranges), model.transform, K, SHAPE)
    assert len(pts.z) and np.all(pts.z > 0) and np.all((pts.u > -0.5) & (pts.u < 127.5))
    assert not np.any(np.isclose(pts.z, 6.0))


def test_points_follow_a_resize_and_a_flip_as_the_intrinsics_do():
    model = lidar_model({"fov": 60}, "test")
    pts = project_scan(_wall_scan(3.0, model), model.transform, K, SHAPE)
    half = pts.transformed((0, 0, 96, 128), (48, 64))
    K2 = K.copy()
    K2[:2] *= 0.5
    K2[0, 2], K2[1, 2] = (63.5 + 0.5) * 0.5 - 0.5, (47.5 + 0.5) * 0.5 - 0.5
    direct = project_scan(_wall_scan(3.0, model), model.transform, K2, (48, 64))
    assert np.allclose(half.u, direct.u) and np.allclose(half.v, direct.v)
    flipped = pts.transformed((0, 0, 96, 128), (96, 128), flip=True)
    assert np.allclose(flipped.u, 127 - pts.u)


@pytest.mark.parametrize("matrix, message", [
    (np.diag([1.0, 1.0, 2.0, 1.0]), "not a rigid transform"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not a rigid transform"),
    (np.eye(3), "4x4"),
    ([[np.nan] * 4] * 4, "NaN"),
])
def test_a_transform_that_is_not_rigid_is_refused(matrix, message):
    with pytest.raises(UserError, match=message):
        rigid_transform(matrix, "lidar.yaml")


def test_the_mount_transform_is_rigid_and_zero_is_the_ideal_level_mount():
    rigid_transform(mount_transform(0.1, 0.02, -0.03, 4, 2, 1), "test")
    level = lidar_model({}, "test").transform
    assert np.allclose(level[:3, :3] @ [1, 0, 0], [0, 0, 1])      # forward is the optical axis


@pytest.mark.parametrize("options, message", [
    ({"fov": 0}, "positive step"), ({"resolution": -1}, "positive step"), ({"noise": -0.1}, "noise"),
    ({"dropout": 1.5}, "dropout"), ({"range_min": 5, "range_max": 1}, "range_min"), ({"colour": 1}, "unknown"),
    ({"tilt": "steep"}, "must be a number"), ({"tilt": float("inf")}, "finite"),
    ({"T_cam_lidar": np.eye(4).tolist(), "tilt": 1}, "not both"), ({"resolution": 1e-6}, "beams"),
])
def test_bad_lidar_models_are_one_line(options, message):
    with pytest.raises(UserError, match=message) as err:
        lidar_model(options, "lidar.yaml")
    assert "\n" not in str(err.value)


def test_lidar_yaml_and_range_files(tmp_path):
    (tmp_path / "lidar.yaml").write_text("fov: 90\nresolution: 1.0\nrange_max: 12\nmount:\n  height: 0.08\n  tilt: 1.5\n")
    model = read_lidar_yaml(tmp_path / "lidar.yaml")
    assert model.beams == 91 and model.range_max == 12 and model.transform[1, 3] == pytest.approx(-0.08)
    np.savetxt(tmp_path / "scan.csv", np.full((1, 91), 2.0), delimiter=",")
    assert read_ranges(tmp_path / "scan.csv", model.beams).shape == (91,)
    with pytest.raises(UserError, match="91 ranges, the LiDAR.s model has 90 beams"):
        read_ranges(tmp_path / "scan.csv", 90)
    (tmp_path / "bad.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(UserError, match="mapping"):
        read_lidar_yaml(tmp_path / "bad.yaml")
