"""Every source's training and validation frames are apart: never one frame in both."""

import h5py
import numpy as np
import pytest
from PIL import Image

from conftest import TINY_DATA
from explorer.data import open_dataset, parse_data_spec, with_lidar
from explorer.errors import UserError

from _bags import scene, write_bag


def _png(path, h=40, w=60, seed=0, depth=False):
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    a = rng.integers(500, 5000, (h, w)).astype(np.uint16) if depth else rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    Image.fromarray(a).save(path)


def _pairs(root, n=20, name="pairs.csv", start=0):
    lines = []
    for i in range(start, start + n):
        _png(root / f"img_{i}.png", seed=i)
        _png(root / f"dep_{i}.png", seed=i, depth=True)
        lines.append(f"img_{i}.png,dep_{i}.png")
    (root / name).write_text("\n".join(lines) + "\n")
    return root / name


def _h5(root, n=12):
    for i in range(n):
        p = root / f"scene_{i % 3}" / f"{i:05d}.h5"
        p.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(p, "w") as f:
            f["rgb"] = np.random.default_rng(i).integers(0, 255, (3, 48, 64), dtype=np.uint8)
            f["depth"] = np.full((48, 64), 2.5, np.float32)
    return root


def _frames(root, n=14):
    for i in range(n):
        _png(root / f"frame_{i:04d}.png", seed=i)
    (root / "intrinsics.txt").write_text("50 50 30 20\n")
    return root


def _sources(tmp, shared):
    yield TINY_DATA
    yield "synthetic-seq:9:6"
    yield f"nyu:{_pairs(tmp / 'pairs')}"
    yield f"nyu:{_pairs(tmp / 'pairs')},val=0.3"
    yield f"nyu:{_h5(tmp / 'h5')}"
    yield f"frames:{_frames(tmp / 'frames')}"
    bag = write_bag(tmp / "run.bag", scene(n=24, h=24, w=32), "ros1")
    yield f"rosbag:{bag}"
    yield f"rosbag-seq:{bag}"
    if shared.is_dir():   # real KITTI frames (raw layout): three, split in name order with one left out
        yield f"kitti:{shared / 'kitti-mini'}"


def test_no_source_serves_a_frame_to_both_splits(tmp_path, monkeypatch):
    from conftest import SHARED
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path / "cache"))
    for spec in _sources(tmp_path, SHARED):
        train, val = (open_dataset(spec, s, (24, 32)) for s in ("train", "val"))
        names = train.frame_names(), val.frame_names()
        assert len(train) and len(val), spec
        assert len(set(names[0])) == len(names[0]) and not set(names[0]) & set(names[1]), spec


def test_a_pairs_csv_validates_on_its_last_tenth_or_its_own_csv(tmp_path):
    csv = _pairs(tmp_path, n=20)
    train, val = (open_dataset(f"nyu:{csv}", s, (24, 32)) for s in ("train", "val"))
    assert (len(train), len(val)) == (18, 2) and val.frame_names()[-1].endswith("img_19.png")
    own = _pairs(tmp_path, n=5, name="val.csv", start=100)
    spec = f"nyu:{csv},val={own}"
    assert len(open_dataset(spec, "train", (24, 32))) == 20 and len(open_dataset(spec, "val", (24, 32))) == 5
    overlapping = _pairs(tmp_path, n=5, name="overlap.csv", start=15)
    with pytest.raises(UserError, match="both list img_15.png"):
        open_dataset(f"nyu:{csv},val={overlapping}", "val", (24, 32))


def test_a_source_too_small_for_two_splits_is_one_line(tmp_path, run_cli):
    code, _, err = run_cli("data", "inspect", "--data", f"frames:{_frames(tmp_path / 'f', n=4)}")
    assert code == 2 and "too few" in err and len(err.strip().splitlines()) == 1
    csv = _pairs(tmp_path / "one", n=1)
    with pytest.raises(UserError, match="too few"):
        open_dataset(f"nyu:{csv}", "train", (24, 32))


def test_inspect_prints_both_splits_and_where_they_part(tmp_path, run_cli):
    code, out, _ = run_cli("data", "inspect", "--data", f"nyu:{_pairs(tmp_path, n=20)}", "--input-size", "24x32")
    assert code == 0 and "train: 18 frames" in out and "val: 2 frames" in out and "no frame is in both splits" in out


@pytest.mark.parametrize("spec, message", [
    ("synthetic,tilt", "KEY=VALUE"), ("synthetic,colour=red", "unknown option 'colour'"),
    ("synthetic,tilt=1,tilt=2", "given twice"), ("synthetic,val=0.2", "generates its own"),
    ("synthetic,fov=-3", "positive step"),
])
def test_bad_data_options_are_one_line(spec, message):
    with pytest.raises(UserError, match=message):
        parse_data_spec(spec)


def test_kitti_refuses_a_lidar_model_it_would_ignore(shared_data):
    with pytest.raises(UserError, match="brings its own scan"):
        parse_data_spec(f"kitti:{shared_data / 'kitti-mini'},tilt=2")


def test_a_spec_is_written_canonically_and_lidar_yaml_joins_it():
    assert str(parse_data_spec("synthetic,tilt=2,height=0.05")) == "synthetic,height=0.05,tilt=2"
    merged = with_lidar("synthetic", {"fov": 120, "mount": {"tilt": 1.5}})
    assert merged == "synthetic,fov=120,tilt=1.5"
    T = np.eye(4)[[2, 0, 1, 3]]   # a rotation (a permutation with determinant +1)
    merged = with_lidar("synthetic", {"T_cam_lidar": T.tolist()})
    assert np.allclose(parse_data_spec(merged).lidar.transform, T)
    with pytest.raises(UserError, match="not a rigid transform"):
        with_lidar("synthetic", {"T_cam_lidar": np.diag([2.0, 1, 1, 1]).tolist()})


def test_lidar_yaml_and_a_spec_that_gives_a_lidar_too_are_one_line(tmp_path, run_cli):
    (tmp_path / "lidar.yaml").write_text("fov: 90\ntilt: 1\n")
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:48:16,tilt=2", "--lidar", tmp_path / "lidar.yaml")
    assert code == 2 and "gives the LiDAR key 'tilt'" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "bad.yaml").write_text("fov: wide\n")
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:48:16", "--lidar", tmp_path / "bad.yaml")
    assert code == 2 and "fov must be a number" in err
