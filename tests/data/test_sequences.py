import numpy as np
import pytest
import torch
from PIL import Image

from explorer.data import open_dataset, parse_data_spec
from explorer.data.sequences import TARGETS_PER_CLIP, scale_intrinsics
from explorer.errors import UserError

SEQ = "synthetic-seq:6:3"


def _png(path, h=40, w=120, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)).save(path)


def _folder(root, n=4, sizes=None):
    for i in range(n):
        h, w = (sizes or {}).get(i, (40, 60))
        _png(root / f"frame_{i:04d}.png", h, w, i)
    (root / "intrinsics.txt").write_text("50 50 30 20\n")
    return root


def _drive(root, n=4):
    """A tiny KITTI raw drive: a wall 10 m ahead, the car moving 1 m forward per frame."""
    date = root / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    (date).mkdir(parents=True)
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\nP_rect_02: 50 0 60 0 0 50 20 0 0 0 1 0\nR_rect_00: 1 0 0 0 1 0 0 0 1\n")
    (date / "calib_velo_to_cam.txt").write_text("R: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0\n")
    (date / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    y, z = np.meshgrid(np.linspace(-6, 6, 121), np.linspace(-1, 1, 21))
    wall = np.c_[np.full(y.size, 10.0), y.ravel(), z.ravel(), np.zeros(y.size)].astype(np.float32)
    lat = 49.0
    metre = 1.0 / (np.cos(np.radians(lat)) * np.pi * 6378137.0 / 180.0)  # degrees of longitude per metre
    for i in range(n):
        _png(drive / "image_02" / "data" / f"{i:010d}.png", seed=i)
        (drive / "velodyne_points" / "data").mkdir(parents=True, exist_ok=True)
        wall.tofile(drive / "velodyne_points" / "data" / f"{i:010d}.bin")
        (drive / "oxts" / "data").mkdir(parents=True, exist_ok=True)
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(f"{lat} {8.0 + i * metre} 110 0 0 0\n")
    return drive


def test_synthetic_sequence_items_are_consistent():
    ds = open_dataset(SEQ, "train", (32, 48))
    assert len(ds) == 6 and ds.max_depth == 10.0 and str(parse_data_spec(SEQ)) == SEQ
    item = ds[1]
    assert item["image"].shape == (3, 32, 48) and item["sources"].shape == (2, 3, 32, 48)
    assert item["depth"].shape == (1, 32, 48) and torch.allclose(item["scan"], item["depth"][0, 16])
    assert item["pose_known"] and item["pose"].shape == (2, 4, 4)
    step = item["pose"][:, :3, 3].norm(dim=1)
    assert 0.02 < float(step[0]) < 0.31 and torch.allclose(step[0], step[1], atol=1e-4)  # smooth motion
    # neighbouring targets of one clip share frames: t+1 of target k is target k+1
    assert torch.equal(ds[0]["sources"][1], ds[1]["image"]) and TARGETS_PER_CLIP == 3
    assert not torch.equal(ds[0]["image"], ds[1]["image"])


def test_intrinsics_follow_crop_and_resize():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 24.5], [0, 0, 1]])
    half = scale_intrinsics(K, (0, 0, 50, 100), (25, 50))
    assert half[0, 0] == 50 and half[0, 2] == pytest.approx(24.5) and half[1, 2] == pytest.approx(12)
    cropped = scale_intrinsics(K, (10, 20, 40, 80), (40, 80))
    assert cropped[0, 2] == pytest.approx(29.5) and cropped[1, 2] == pytest.approx(14.5)


def test_frame_folder(tmp_path):
    root = _folder(tmp_path / "f", n=12)
    train, val = open_dataset(f"frames:{root}", "train", (32, 48)), open_dataset(f"frames:{root}", "val", (32, 48))
    # 10 targets: the last validates, the two before it are left out (their neighbours are validation frames)
    assert len(train) == 7 and len(val) == 1
    assert not set(train.frame_names()) & set(val.frame_names())
    item = train[0]
    assert item["sources"].shape == (2, 3, 32, 48) and not item["pose_known"]
    assert float(item["K"][0, 0]) == pytest.approx(50 * 48 / 60)


def test_kitti_drive_with_oxts_poses(tmp_path):
    drive = _drive(tmp_path, n=6)
    ds = open_dataset(f"kitti-seq:{drive}", "train", (32, 96))
    item = ds[0]
    assert item["pose_known"] and ds.max_depth == 80.0
    # the car moved 1 m forward: the previous camera is 1 m behind the target (z), the next 1 m ahead
    assert torch.allclose(item["pose"][0, :3, 3], torch.tensor([0.0, 0.0, 1.0]), atol=0.02)
    assert torch.allclose(item["pose"][1, :3, 3], torch.tensor([0.0, 0.0, -1.0]), atol=0.02)
    valid = item["depth"][item["depth"] > 0]
    assert valid.numel() and torch.allclose(valid, torch.tensor(10.0), atol=0.01)
    assert (item["scan"] > 0).any() and torch.allclose(item["scan"][item["scan"] > 0], torch.tensor(10.0), atol=0.01)
    # the Garg crop: no ground truth in the top rows
    assert not (item["depth"][0, :10] > 0).any()


def test_real_kitti_mini_is_not_a_sequence(shared_data, run_cli):
    # kitti-mini holds 3 unrelated object-detection frames: no drive layout, one clear line
    code, _, err = run_cli("data", "inspect", "--data", f"kitti-seq:{shared_data / 'kitti-mini'}")
    assert code == 2 and "image_02/data" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("damage, message", [
    ("gap", "frame 2 is missing"),
    ("intrinsics", "missing intrinsics.txt"),
    ("sizes", "differ in size"),
    ("velodyne", "no point cloud for frame"),
    ("few", "at least 3"),
])
def test_malformed_sequences_are_one_line_exit_2(tmp_path, run_cli, damage, message):
    if damage == "velodyne":
        drive = _drive(tmp_path)
        (drive / "velodyne_points" / "data" / "0000000002.bin").unlink()
        spec = f"kitti-seq:{drive}"
    else:
        root = _folder(tmp_path / "f", n=2 if damage == "few" else 5,
                       sizes={3: (40, 64)} if damage == "sizes" else None)
        if damage == "gap":
            (root / "frame_0002.png").unlink()
        if damage == "intrinsics":
            (root / "intrinsics.txt").unlink()
        spec = f"frames:{root}"
    code, _, err = run_cli("train", "paper", "--supervision", "self", "--data", spec, "--steps", "1",
                           "--out", tmp_path / "x.pt")
    assert code == 2 and message in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_frame_folder_with_a_real_lidars_scans(tmp_path):
    from explorer.scan import lidar_model, simulate_ranges
    root = _folder(tmp_path / "f", n=14)
    (root / "lidar.yaml").write_text("fov: 100\nresolution: 0.5\nrange_max: 8\nheight: 0.04\ntilt: 3\n")
    model = lidar_model({"fov": 100, "resolution": 0.5, "range_max": 8, "height": 0.04, "tilt": 3}, "test")
    K = np.array([[50.0, 0, 30], [0, 50.0, 20], [0, 0, 1]])
    depth = np.full((40, 60), 2.5, np.float32)
    for p in sorted(root.glob("frame_*.png")):
        (root / "depth").mkdir(exist_ok=True)
        Image.fromarray((depth * 1000).astype(np.uint16)).save(root / "depth" / f"{p.stem}.png")
        (root / "scans").mkdir(exist_ok=True)
        np.save(root / "scans" / f"{p.stem}.npy", simulate_ranges(depth, K, model).ranges)
    item = open_dataset(f"frames:{root}", "train", (40, 60))[0]
    hit = item["scan"] > 0
    assert hit.float().mean() > 0.9 and torch.allclose(item["scan"][hit], torch.tensor(2.5), atol=0.02)
    # 3 degrees down, 4 cm up, on a wall 2.5 m away: 50 * (tan 3 deg - 0.04 / 2.5) = 1.8 rows below the centre
    assert abs(float(item["scan_rows"][hit].float().mean()) - (20 + 1.82)) < 0.6   # cy = 20
    (root / "scans" / "frame_0005.npy").unlink()
    with pytest.raises(UserError, match="no scan for frame frame_0005"):
        open_dataset(f"frames:{root}", "train", (40, 60))
    (root / "lidar.yaml").unlink()
    with pytest.raises(UserError, match="write lidar.yaml"):
        open_dataset(f"frames:{root}", "train", (40, 60))


def test_a_frame_folder_without_poses_takes_its_validation_motion_from_the_scans(tmp_path):
    """A camera driving 5 cm a frame toward a wall, with its LiDAR's scans and no poses.txt, no depth:
    the validation samples carry the motion the scans measure; training learns its own."""
    from _bags import MOUNT, scene
    sc = scene(n=24, h=48, w=64, whole_room=True)
    root = tmp_path / "f"
    (root / "scans").mkdir(parents=True)
    for i, (rgb, ranges) in enumerate(zip(sc.rgb, sc.ranges)):
        Image.fromarray(rgb).save(root / f"frame_{i:04d}.png")
        np.save(root / "scans" / f"frame_{i:04d}.npy", ranges)
    (root / "lidar.yaml").write_text("".join(f"{k}: {v}\n" for k, v in MOUNT.items()))
    K = sc.K
    (root / "intrinsics.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    val = open_dataset(f"frames:{root}", "val", (48, 64))
    items = [val[i] for i in range(len(val))]
    assert items and all(bool(it["pose_known"]) for it in items)
    assert all(abs(float(it["pose"][1, 2, 3]) + 0.05) < 0.005 for it in items)   # the next frame: 5 cm nearer
    assert not any(bool(open_dataset(f"frames:{root}", "train", (48, 64))[i]["pose_known"]) for i in range(3))
