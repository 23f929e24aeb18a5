import gc
import weakref

import h5py
import numpy as np
import pytest
import torch

from explorer.data import ScanConfig, open_dataset, parse_data_spec, scan_from_image, simulate_scan
from explorer.data.readers import KittiRaw
from explorer.data.synthetic import SyntheticConfig, ensure_synthetic, render_scene
from explorer.errors import UserError
from explorer.metrics import MetricAverager, batch_depth_metrics, depth_metrics
from explorer.model import interpolate_scan
from conftest import TINY_DATA


def test_synthetic_render_deterministic_with_depth_range():
    a = render_scene(np.random.default_rng([0, 3]), 64, 80)
    b = render_scene(np.random.default_rng([0, 3]), 64, 80)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    rgb, depth = a
    assert rgb.shape == (64, 80, 3) and rgb.dtype == np.uint8 and depth.shape == (64, 80)
    assert 0.3 < depth.min() and depth.max() <= 10.0
    assert rgb.std() > 10  # textured and shaded, not flat


def test_synthetic_dataset_items():
    ds = open_dataset(TINY_DATA, "val", (64, 96))
    assert len(ds) == 16
    item = ds[0]
    assert item["image"].shape == (3, 64, 96) and 0 <= item["image"].min() and item["image"].max() <= 1
    assert item["depth"].shape == (1, 64, 96) and item["scan"].shape == (96,)
    assert item["scan_row"] == 32
    assert torch.allclose(item["scan"], item["depth"][0, 32])


def test_synthetic_frames_held_once_as_stored():
    """Data sets of one split at two sizes read one copy of its frames, depth kept as the file's float16
    and read as float32 with the file's values; the copy goes with the last data set."""
    small, large = open_dataset(TINY_DATA, "train", (64, 64)), open_dataset(TINY_DATA, "train", (224, 224), seed=3)
    assert small.frames is large.frames and small.frames.depth.dtype == np.float16
    with h5py.File(ensure_synthetic(SyntheticConfig(train=48, val=16)), "r") as f:
        stored = np.asarray(f["train"]["depth"][5], dtype=np.float32)
    frame = large.frames[5]
    assert frame.depth.dtype == np.float32 and np.array_equal(frame.depth, stored)
    assert np.array_equal(large[5]["depth"][0].numpy(), stored)
    held = weakref.ref(small.frames)
    del small, large, frame
    gc.collect()
    assert held() is None


def test_scan_simulation():
    depth = np.tile(np.linspace(1, 12, 20, dtype=np.float32), (10, 1))
    scan, row = simulate_scan(depth, ScanConfig(row=3, max_range=10.0))
    assert row == 3 and scan[0] == pytest.approx(1.0) and (scan[depth[3] > 10] == 0).all()
    sparse, _ = simulate_scan(depth, ScanConfig(points=5, max_range=20))
    assert (sparse > 0).sum() == 5
    dropped, _ = simulate_scan(depth, ScanConfig(dropout=0.5, max_range=20), np.random.default_rng(0))
    assert 0 < (dropped > 0).sum() < 20
    noisy, _ = simulate_scan(depth, ScanConfig(noise=0.1, max_range=20), np.random.default_rng(0))
    assert 0 < np.abs(noisy - depth[5]).max() < 1


def test_scan_from_image_collapses_a_ring():
    img = np.zeros((10, 6), np.float32)
    img[4, [0, 2]] = [3, 4]
    img[5, 3] = 7
    scan, row = scan_from_image(img)
    assert row == 4 and scan.tolist() == [3, 0, 4, 7, 0, 0]


def test_metrics_reproduce_fastdepth(shared_data):
    d = shared_data / "fastdepth-frame"
    m = depth_metrics(np.load(d / "pred.npy")[0, 0], np.load(d / "depth.npy"))
    assert m["rmse"] == pytest.approx(0.618, abs=5e-4)
    assert m["rel"] == pytest.approx(0.140, abs=5e-4)
    assert m["delta1"] == pytest.approx(0.777, abs=5e-4)


def test_metrics_by_hand():
    m = depth_metrics(np.array([1.0, 2.0, 9.0]), np.array([1.0, 4.0, 0.0]))
    assert m["rmse"] == pytest.approx(np.sqrt(2.0)) and m["mae"] == pytest.approx(1.0)
    assert m["rel"] == pytest.approx(0.25) and m["delta1"] == pytest.approx(0.5)


def test_nyu_csv_real_frames(shared_data):
    spec = f"nyu:{shared_data / 'nyu-mini' / 'nyu2_mini_test.csv'}"
    train, val = (open_dataset(spec, s, (224, 224), train_augment=False) for s in ("train", "val"))
    assert (len(train), len(val)) == (9, 1)   # the listing's last tenth validates
    assert not set(train.frame_names()) & set(val.frame_names())
    avg = MetricAverager()
    for it in [ds[i] for ds in (train, val) for i in range(len(ds))]:
        assert it["depth"].max() < 10.5 and it["depth"].min() > 0.5
        avg.add(depth_metrics(interpolate_scan(it["scan"][None], 224)[0], it["depth"]))
    assert 0.6 < avg.result()["rmse"] < 1.6  # the paper: 0.987 on the full validation set


def _nyu_h5(root, n=2, **override):
    for i in range(n):
        p = root / "val" / "scene_a" / f"{i:05d}.h5"
        p.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(p, "w") as f:
            f["rgb"] = override.get("rgb", np.random.default_rng(i).integers(0, 255, (3, 480, 640), dtype=np.uint8))
            f["depth"] = override.get("depth", np.full((480, 640), 2.5, np.float32))
    return root


def test_nyu_h5_reader(tmp_path):
    ds = open_dataset(f"nyu:{_nyu_h5(tmp_path)}", "val", (64, 64))
    assert len(ds) == 2
    it = ds[1]
    assert it["image"].shape == (3, 64, 64) and torch.allclose(it["depth"], torch.tensor(2.5))
    train = open_dataset(f"nyu:{tmp_path}", "val", (64, 64), train_augment=True)
    assert train[0]["depth"].max() <= 2.5 + 1e-6  # scale augmentation divides depth by s >= 1


@pytest.mark.parametrize("override, msg", [
    ({"depth": np.full((480, 640), np.nan, np.float32)}, "NaN"),
    ({"depth": np.ones((100, 100), np.float32)}, "differ"),
])
def test_nyu_h5_malformed(tmp_path, override, msg):
    ds = open_dataset(f"nyu:{_nyu_h5(tmp_path, 1, **override)}", "val", (64, 64))
    with pytest.raises(UserError, match=msg):
        ds[0]


def test_missing_key_and_empty_folder(tmp_path, run_cli):
    p = tmp_path / "val" / "s" / "00000.h5"
    p.parent.mkdir(parents=True)
    with h5py.File(p, "w") as f:
        f["rgb"] = np.zeros((3, 480, 640), np.uint8)
    code, _, err = run_cli("data", "inspect", "--data", f"nyu:{tmp_path}")
    assert code == 2 and "missing dataset" in err and "00000.h5" in err and len(err.strip().splitlines()) == 1
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_cli("data", "inspect", "--data", f"nyu:{empty}")
    assert code == 2 and "no .h5 files" in err
    code, _, err = run_cli("data", "inspect", "--data", "imagenet:/x")
    assert code == 2 and "unknown data set" in err


def test_kitti_raw_real_frames(shared_data):
    raw = KittiRaw(shared_data / "kitti-mini")
    f = raw[0]
    assert f.rgb.shape[2] == 3 and f.depth.shape == f.rgb.shape[:2]
    assert (f.depth > 0).mean() > 0.01 and f.depth.max() < 120
    ring = f.scan_image > 0
    assert 0 < ring.sum() < (f.depth > 0).sum() / 10  # one laser ring, not the whole cloud
    ds = open_dataset(f"kitti:{shared_data / 'kitti-mini'}", "val", (224, 896))
    it = ds[0]
    assert it["image"].shape == (3, 224, 896) and (it["scan"] > 0).sum() > 50


def test_kitti_h5_layout(tmp_path):
    p = tmp_path / "val" / "drive" / "0000000001.h5"
    p.parent.mkdir(parents=True)
    depth = np.zeros((375, 1242), np.float32)
    depth[200:, ::7] = 12.0
    with h5py.File(p, "w") as f:
        f["rgb"] = np.zeros((3, 375, 1242), np.uint8)
        f["depth"] = depth
    it = open_dataset(f"kitti:{tmp_path}", "val", (64, 256))[0]
    assert it["depth"].shape == (1, 64, 256) and set(np.unique(it["depth"].numpy())) <= {0.0, 12.0}


def test_data_spec_parsing():
    assert parse_data_spec("synthetic").train == 2000
    assert parse_data_spec("synthetic:10:4").val == 4
    with pytest.raises(UserError):
        parse_data_spec("nyu:/does/not/exist")
    with pytest.raises(UserError):
        parse_data_spec("synthetic:many")


def test_metrics_of_tensors_and_arrays_agree_with_the_batch_metrics():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 1, 8, 8, generator=g) * 5
    target = torch.rand(2, 1, 8, 8, generator=g) * 5 * (torch.rand(2, 1, 8, 8, generator=g) > 0.3)
    pred[0, 0, 0, 0] = 0.0   # a non-positive prediction: a failure in every delta
    batch = batch_depth_metrics(pred, target)
    for i in range(2):
        from_tensor, from_array = depth_metrics(pred[i], target[i]), depth_metrics(pred[i].numpy(), target[i].numpy())
        assert from_tensor == from_array
        assert from_array == pytest.approx(batch[i], rel=1e-9)
