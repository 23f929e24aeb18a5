"""Mistakes in a LiDAR model (lidar.yaml, data options) and in camera intrinsics that were once taken
silently: each is now one UserError line that says what is wrong and what to keep, and the files the
guides show still parse."""

import math
import re
from pathlib import Path

import numpy as np
import pytest

from explorer.errors import UserError
from explorer.scan import check_principal_point, lidar_model, read_intrinsics, read_lidar_yaml

DOCS = Path(__file__).resolve().parents[1] / "docs"


def refused(call, *args) -> str:
    with pytest.raises(UserError) as err:
        call(*args)
    message = str(err.value)
    assert "\n" not in message
    return message


# -- 1. booleans where numbers go ----------------------------------------------------------------
@pytest.mark.parametrize("key", ["fov", "resolution", "noise", "height", "tilt", "angle_min"])
def test_a_boolean_is_not_a_number(key):
    message = refused(lidar_model, {key: True}, "lidar.yaml")
    assert message.startswith(f"lidar.yaml: {key} must be a number, got true") and "write the number" in message


def test_a_yaml_boolean_in_a_file_and_in_the_mount_matrix_is_refused(tmp_path):
    (tmp_path / "lidar.yaml").write_text("fov: true\n")
    assert "fov must be a number, got true" in refused(read_lidar_yaml, tmp_path / "lidar.yaml")
    (tmp_path / "mount.yaml").write_text("dropout: false\n")
    assert "dropout must be a number, got false" in refused(read_lidar_yaml, tmp_path / "mount.yaml")
    identity = [[i == j for j in range(4)] for i in range(4)]
    assert "T_cam_lidar holds true/false" in refused(lidar_model, {"T_cam_lidar": identity}, "lidar.yaml")


# -- 2. more than a full turn ------------------------------------------------------------------------
def test_a_field_of_view_over_a_full_turn_is_refused():
    message = refused(lidar_model, {"fov": 720}, "lidar.yaml")
    assert "fov 720 is more than a full turn" in message and "360 degrees" in message
    message = refused(lidar_model, {"angle_min": -4, "angle_max": 4}, "lidar.yaml")
    assert "more than a full turn" in message and "radians" in message
    assert lidar_model({"fov": 360, "resolution": 1}, "t").beams == 361
    # a LaserScan's full turn, its float32 angles written out rounded, is a full turn
    assert lidar_model({"angle_min": -3.1416, "angle_max": 3.1416, "angle_increment": 0.01}, "t").beams == 629


# -- 3. a field of view given two ways ---------------------------------------------------------------
@pytest.mark.parametrize("extra, named", [({"angle_min": -1}, "fov and angle_min"),
                                          ({"angle_max": 1}, "fov and angle_max"),
                                          ({"angle_min": -1, "angle_max": 1}, "fov and angle_min and angle_max")])
def test_fov_and_angle_limits_together_are_refused(extra, named):
    message = refused(lidar_model, {"fov": 180, **extra}, "lidar.yaml")
    assert message.startswith(f"lidar.yaml: {named} both give the field of view; keep fov")


def test_resolution_and_angle_increment_together_are_refused():
    message = refused(lidar_model, {"resolution": 0.5, "angle_increment": 0.01}, "lidar.yaml")
    assert "resolution and angle_increment both give the step" in message


def test_a_data_spec_mixing_fov_and_angles_is_refused():
    from explorer.data.spec import parse_data_spec
    assert "both give the field of view" in refused(parse_data_spec, "synthetic,fov=180,angle_min=-1")


# -- 4. a key given twice ----------------------------------------------------------------------------
def test_a_key_given_twice_in_lidar_yaml_is_refused(tmp_path):
    (tmp_path / "lidar.yaml").write_text("fov: 180\nresolution: 1\nfov: 90\n")
    message = refused(read_lidar_yaml, tmp_path / "lidar.yaml")
    assert message == f"{tmp_path / 'lidar.yaml'}: the key 'fov' is given twice (lines 1 and 3); keep one"
    (tmp_path / "nested.yaml").write_text("mount:\n  tilt: 1\n  tilt: 2\n")
    assert "the key 'tilt' is given twice (lines 2 and 3)" in refused(read_lidar_yaml, tmp_path / "nested.yaml")
    (tmp_path / "quoted.yaml").write_text("fov: 180\n'fov': 90\n")
    assert "'fov' is given twice" in refused(read_lidar_yaml, tmp_path / "quoted.yaml")


def test_a_mount_key_given_under_mount_and_beside_it_is_refused(tmp_path):
    (tmp_path / "lidar.yaml").write_text("tilt: 1\nmount:\n  tilt: 2\n")
    assert "'tilt' is given both under mount: and beside it" in refused(read_lidar_yaml, tmp_path / "lidar.yaml")
    assert "mount must be a mapping" in refused(lidar_model, {"mount": 5}, "lidar.yaml")
    assert "'fov' under mount: is not a mount key" in refused(lidar_model, {"mount": {"fov": 90}}, "lidar.yaml")


def test_lidar_yaml_mistakes_through_the_cli_exit_2_with_one_line(tmp_path, run_cli, monkeypatch):
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path / "cache"))
    (tmp_path / "twice.yaml").write_text("fov: 180\nfov: 90\n")
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:48:16", "--lidar", tmp_path / "twice.yaml")
    assert code == 2 and "'fov' is given twice" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "mixed.yaml").write_text("fov: 180\nangle_min: -1\n")
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:48:16", "--lidar", tmp_path / "mixed.yaml")
    assert code == 2 and f"{tmp_path / 'mixed.yaml'}: fov and angle_min both" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_the_yaml_safety_of_the_package_still_holds(tmp_path):
    bomb = "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 10)}]\n" for p, c in zip("abcdefg", "bcdefgh"))
    (tmp_path / "bomb.yaml").write_text(bomb)
    assert "aliases expand" in refused(read_lidar_yaml, tmp_path / "bomb.yaml")
    (tmp_path / "bad.yaml").write_text("fov: [1\n")
    assert "not valid YAML" in refused(read_lidar_yaml, tmp_path / "bad.yaml")


# -- 5. a principal point off the image --------------------------------------------------------------
def test_a_principal_point_outside_the_image_is_refused(tmp_path):
    (tmp_path / "intrinsics.txt").write_text("40 40 1600 1600\n")
    K = read_intrinsics(tmp_path / "intrinsics.txt")   # the file alone is a camera matrix
    message = refused(check_principal_point, K, (32, 32), "intrinsics.txt")
    assert message.startswith("intrinsics.txt: the principal point cx=1600, cy=1600 lies outside the 32x32 image")
    assert "cx near 16" in message
    left_of_it = np.array([[40, 0, -3], [0, 40, 10], [0, 0, 1]], float)
    assert "outside the 64x48 image" in refused(check_principal_point, left_of_it, (48, 64, 3), "K")


@pytest.mark.parametrize("cx, cy", [(0, 0), (32, 32), (-0.5, -0.5), (15.5, 15.5), (31.5, 0)])
def test_a_principal_point_inside_the_image_or_on_its_edge_is_accepted(cx, cy):
    check_principal_point(np.array([[40, 0, cx], [0, 40, cy], [0, 0, 1]], float), (32, 32), "K")


# -- what the guides show still parses ---------------------------------------------------------------
def _yaml_blocks(page: Path, marker: str) -> list[str]:
    return [b for b in re.findall(r"```yaml\n(.*?)```", page.read_text(), re.S) if marker in b]


@pytest.mark.parametrize("page, marker", [("guides/data.md", "resolution:"), ("guides/deploying.md", "fov: 270")])
def test_the_lidar_yaml_the_guides_show_still_parses(tmp_path, page, marker):
    blocks = _yaml_blocks(DOCS / page, marker)
    assert blocks, f"no lidar.yaml example in {page}"
    (tmp_path / "lidar.yaml").write_text(blocks[0])
    model = read_lidar_yaml(tmp_path / "lidar.yaml")
    assert model.angle_max - model.angle_min <= 2 * math.pi and model.beams > 1


def test_valid_files_still_parse(tmp_path):
    (tmp_path / "lidar.yaml").write_text("angle_min: -2.356\nangle_max: 2.356\nangle_increment: 0.0087\n"
                                         "range_max: 12\nmount:\n  height: 0.08\n  tilt: 1.5\n")
    model = read_lidar_yaml(tmp_path / "lidar.yaml")
    assert model.angle_min == -2.356 and model.transform[1, 3] == pytest.approx(-0.08)
    (tmp_path / "intrinsics.txt").write_text("520 520 319.5 239.5\n")
    K = read_intrinsics(tmp_path / "intrinsics.txt")
    check_principal_point(K, (480, 640), "intrinsics.txt")
    assert lidar_model({"fov": "180", "resolution": "0.5", "tilt": "2"}, "data").beams == 361
