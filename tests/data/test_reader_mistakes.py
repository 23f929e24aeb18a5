"""Mistakes in the files of real data sets (NYU CSV pairs, KITTI object-detection folders, KITTI raw
drives, frame folders): each is one UserError line naming the file, never a traceback or wrong depths."""

import numpy as np
import pytest
from PIL import Image

from explorer.data import open_dataset
from explorer.data.readers import read_calib
from explorer.errors import UserError

SIZE = (32, 32)
# velodyne (x forward, y left, z up) to camera (x right, y down, z forward)
VELO_TO_CAM = "0 -1 0 0 0 0 -1 0 1 0 0 0"


def _rgb_png(path, h=40, w=60, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)).save(path)


def _depth_png(path, mode="I;16", h=40, w=60):
    """A flat wall 3 m away, as 16-bit millimetres or (the mistake) 8-bit grey or palette."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if mode == "I;16":
        Image.fromarray(np.full((h, w), 3000, np.uint16)).save(path)
    else:
        Image.fromarray(np.full((h, w), 30, np.uint8)).convert(mode).save(path)


def _nyu_csv(root, n=4, depth_mode="I;16"):
    lines = ["image,depth"]
    for i in range(n):
        _rgb_png(root / f"image_{i}.png", seed=i)
        _depth_png(root / f"depth_{i}.png", depth_mode)
        lines.append(f"image_{i}.png,depth_{i}.png")
    (root / "pairs.csv").write_text("\n".join(lines) + "\n")
    return root / "pairs.csv"


def _wall_points(distance=10.0):
    y, z = np.meshgrid(np.linspace(-6, 6, 121), np.linspace(-1, 1, 21))
    return np.c_[np.full(y.size, distance), y.ravel(), z.ravel(), np.zeros(y.size)].astype(np.float32)


def _kitti_folder(root, n=3):
    """KITTI's object-detection layout, a wall 10 m ahead; the val split is the last frame."""
    for sub in ("image_2", "velodyne", "calib"):
        (root / sub).mkdir(parents=True)
    for i in range(n):
        _rgb_png(root / "image_2" / f"{i:06d}.png", seed=i)
        _wall_points().tofile(root / "velodyne" / f"{i:06d}.bin")
        (root / "calib" / f"{i:06d}.txt").write_text(
            "P2: 50 0 30 0 0 50 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
            f"Tr_velo_to_cam: {VELO_TO_CAM}\n")
    return root


def _kitti_drive(root, n=6):
    """A KITTI raw drive (no OXTS), a wall 10 m ahead; the val split's one target is frame 4."""
    date = root / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    date.mkdir(parents=True)
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\nP_rect_02: 50 0 30 0 0 50 20 0 0 0 1 0\nR_rect_00: 1 0 0 0 1 0 0 0 1\n")
    (date / "calib_velo_to_cam.txt").write_text("R: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0\n")
    for i in range(n):
        _rgb_png(drive / "image_02" / "data" / f"{i:010d}.png", seed=i)
        (drive / "velodyne_points" / "data").mkdir(parents=True, exist_ok=True)
        _wall_points().tofile(drive / "velodyne_points" / "data" / f"{i:010d}.bin")
    return drive


def _refused(spec, match, split="val"):
    """The one-line UserError that opening ``spec`` and reading its first item raises."""
    with pytest.raises(UserError, match=match) as exc:
        open_dataset(spec, split, SIZE)[0]
    assert "\n" not in str(exc.value)
    return str(exc.value)


@pytest.fixture
def layouts(tmp_path):
    return {"nyu": _nyu_csv(tmp_path / "nyu"), "kitti": _kitti_folder(tmp_path / "kitti"),
            "kitti-seq": _kitti_drive(tmp_path / "seq")}


def test_undamaged_layouts_read(layouts):
    # the layouts the other tests damage are valid as built: each damage alone is what is refused
    nyu = open_dataset(f"nyu:{layouts['nyu']}", "val", SIZE)[0]
    assert np.allclose(nyu["depth"].numpy(), 3.0)
    for kind in ("kitti", "kitti-seq"):
        depth = open_dataset(f"{kind}:{layouts[kind]}", "val", SIZE)[0]["depth"].numpy()
        assert (depth > 0).any() and np.allclose(depth[depth > 0], 10.0, atol=0.01)


# -- NYU CSV ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("content", [
    pytest.param("png", id="an image"),
    pytest.param(bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8)), id="random bytes"),
    pytest.param("image_0.png,depth_0.png\n".encode("utf-16"), id="utf-16"),
    pytest.param("image_0.png,depth_0.png\n".encode("utf-16-le"), id="utf-16 without a byte-order mark"),
])
def test_a_csv_that_is_not_utf8_text(tmp_path, content):
    csv = _nyu_csv(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_bytes((tmp_path / "image_0.png").read_bytes() if content == "png" else content)
    message = _refused(f"nyu:{bad}", "not a UTF-8 text CSV of image,depth pairs")
    assert str(bad) in message
    # the same file as the validation CSV of its own
    assert str(bad) in _refused(f"nyu:{csv},val={bad}", "not a UTF-8 text CSV")
    assert str(bad) in _refused(f"nyu:{csv},val={bad}", "not a UTF-8 text CSV", split="train")


def test_a_csv_with_a_byte_order_mark_reads(tmp_path):
    csv = _nyu_csv(tmp_path)
    csv.write_bytes(csv.read_text().split("\n", 1)[1].encode("utf-8-sig"))  # no header: the mark is on a path
    train = open_dataset(f"nyu:{csv}", "train", SIZE, train_augment=False)
    assert len(train) == 3 and np.allclose(train[0]["depth"].numpy(), 3.0)


def test_the_mistake_is_one_line_exit_2(tmp_path, run_cli):
    bad = tmp_path / "bad.csv"
    bad.write_bytes("a.png,b.png\n".encode("utf-16"))
    code, _, err = run_cli("data", "inspect", "--data", f"nyu:{bad}")
    assert code == 2 and "not a UTF-8 text CSV" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("lines, line", [
    (["image_0.png,depth_0.png", "image_1.png,depth_1.png", "image_2.png"], 3),
    (["image,depth", "image_0.png,depth_0.png", "image_1.png"], 3),
    (["image,depth", "", "image_0.png,depth_0.png", "", "image_1.png,", "image_2.png,depth_2.png"], 5),
    (["image_0.png"], 1),
])
def test_csv_errors_name_the_files_own_line(tmp_path, lines, line):
    _nyu_csv(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    _refused(f"nyu:{bad}", rf"bad.csv: line {line} does not have two columns")


@pytest.mark.parametrize("mode", ["L", "P"])
def test_8_bit_depth_in_a_csv_is_refused(tmp_path, mode):
    csv = _nyu_csv(tmp_path, depth_mode=mode)
    message = _refused(f"nyu:{csv}", "depth must be a 16-bit PNG in millimetres")
    assert "depth_3.png" in message


def test_8_bit_copy_of_a_real_nyu_depth_is_refused(tmp_path, shared_data):
    real = shared_data / "nyu-mini"
    for i in range(3):
        Image.open(real / f"image_{i}.png").save(tmp_path / f"image_{i}.png")
        Image.open(real / f"depth_{i}.png").save(tmp_path / f"depth_{i}.png")
    # what an export to 8 bits does: millimetres / 256, as a viewer would show them
    depth = np.asarray(Image.open(real / "depth_2.png")).astype(np.float64)
    Image.fromarray((depth / 256).astype(np.uint8)).save(tmp_path / "depth_2.png")
    csv = tmp_path / "pairs.csv"
    csv.write_text("".join(f"image_{i}.png,depth_{i}.png\n" for i in range(3)))
    assert 0.5 < float(open_dataset(f"nyu:{csv}", "train", SIZE, train_augment=False)[0]["depth"].max()) < 10.5
    _refused(f"nyu:{csv}", r"depth_2.png: depth must be a 16-bit PNG")


@pytest.mark.parametrize("mode", ["L", "P", "RGB"])
def test_8_bit_depth_in_a_frame_folder_is_refused(tmp_path, mode):
    root = tmp_path / "f"
    for i in range(6):
        _rgb_png(root / f"frame_{i:04d}.png", seed=i)
        _depth_png(root / "depth" / f"frame_{i:04d}.png", mode)
    (root / "intrinsics.txt").write_text("50 50 30 20\n")
    _refused(f"frames:{root}", r"frame_0004.png: depth must be a 16-bit PNG in millimetres")


# -- KITTI: Velodyne scans -------------------------------------------------------------------------
@pytest.mark.parametrize("size", [0, 16 * 10 + 4, 16 * 10 + 1])
def test_a_truncated_or_empty_velodyne_scan_is_refused(layouts, size):
    for kind, velo in (("kitti", layouts["kitti"] / "velodyne" / "000002.bin"),
                       ("kitti-seq", layouts["kitti-seq"] / "velodyne_points" / "data" / "0000000004.bin")):
        velo.write_bytes(velo.read_bytes()[:size])
        message = _refused(f"{kind}:{layouts[kind]}", "a truncated or empty Velodyne scan")
        assert str(velo) in message and "16 bytes" in message


# -- KITTI: calibration ----------------------------------------------------------------------------
def _replace_line(path, key, value):
    lines = [f"{key}: {value}" if line.startswith(f"{key}:") else line for line in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("key, value, need", [
    ("P2", "1 2 3", 12), ("R0_rect", "1 0 0 0 1 0", 9), ("Tr_velo_to_cam", f"{VELO_TO_CAM} 0 0 0 1", 12),
])
def test_kitti_calibration_of_the_wrong_count(layouts, key, value, need):
    calib = layouts["kitti"] / "calib" / "000002.txt"
    _replace_line(calib, key, value)
    message = _refused(f"kitti:{layouts['kitti']}", rf"{key} has {len(value.split())} number\(s\), needs {need}")
    assert str(calib) in message


@pytest.mark.parametrize("name, key, value, need", [
    ("calib_cam_to_cam.txt", "P_rect_02", "1 2 3", 12),
    ("calib_cam_to_cam.txt", "R_rect_00", "1 0 0 0 1 0 0 0 1 0", 9),
    ("calib_velo_to_cam.txt", "R", "1 0 0", 9),
    ("calib_velo_to_cam.txt", "T", "0 0", 3),
])
def test_kitti_drive_calibration_of_the_wrong_count(layouts, name, key, value, need):
    calib = layouts["kitti-seq"].parent / name
    _replace_line(calib, key, value)
    message = _refused(f"kitti-seq:{layouts['kitti-seq']}", rf"{key} has {len(value.split())} number\(s\), "
                       rf"needs {need}")
    assert str(calib) in message


@pytest.mark.parametrize("broken", ["fx", "fy", "row"])
def test_a_projection_with_a_zero_focal_length_is_refused(layouts, broken):
    index = {"fx": 0, "fy": 5, "row": 10}[broken]          # P[0, 0], P[1, 1], P[2, 2] row by row
    for kind, calib, key in (("kitti", layouts["kitti"] / "calib" / "000002.txt", "P2"),
                             ("kitti-seq", layouts["kitti-seq"].parent / "calib_cam_to_cam.txt", "P_rect_02")):
        line = next(x for x in calib.read_text().splitlines() if x.startswith(f"{key}:"))
        values = line.split(":", 1)[1].split()
        values[index] = "0"
        _replace_line(calib, key, " ".join(values))
        message = _refused(f"{kind}:{layouts[kind]}", f"{key} is not a camera projection")
        assert str(calib) in message and "must be positive" in message


def _scaled(values, factor):
    v = np.array(values.split(), float)
    if len(v) == 12:
        v.reshape(3, 4)[:, :3] *= factor
    else:
        v *= factor
    return " ".join(f"{x:g}" for x in v)


@pytest.mark.parametrize("factor", [2.0, -1.0])
def test_a_non_rigid_velodyne_to_camera_transform_is_refused(layouts, factor):
    calib = layouts["kitti"] / "calib" / "000002.txt"
    _replace_line(calib, "Tr_velo_to_cam", _scaled(VELO_TO_CAM, factor))
    message = _refused(f"kitti:{layouts['kitti']}", "Tr_velo_to_cam is not a rigid transform")
    assert str(calib) in message
    seq_calib = layouts["kitti-seq"].parent / "calib_velo_to_cam.txt"
    _replace_line(seq_calib, "R", _scaled("0 -1 0 0 0 -1 1 0 0", factor))
    message = _refused(f"kitti-seq:{layouts['kitti-seq']}", "R is not a rigid transform")
    assert str(seq_calib) in message


def test_real_kitti_calibration_is_rigid_and_a_scaled_copy_is_not(tmp_path, shared_data):
    real = shared_data / "kitti-mini"
    for sub in ("image_2", "velodyne", "calib"):
        (tmp_path / sub).mkdir()
        for f in (real / sub).iterdir():
            if sub == "calib":
                read_calib(f)   # the real files pass the checks
                (tmp_path / sub / f.name).write_text(f.read_text())
            else:
                (tmp_path / sub / f.name).symlink_to(f)
    calib = tmp_path / "calib" / "000002.txt"
    line = next(x for x in calib.read_text().splitlines() if x.startswith("Tr_velo_to_cam:"))
    _replace_line(calib, "Tr_velo_to_cam", _scaled(line.split(":", 1)[1], 2.0))
    _refused(f"kitti:{tmp_path}", r"000002.txt: Tr_velo_to_cam is not a rigid transform")
