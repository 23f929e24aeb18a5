"""ROS bags (ROS 1, ROS 2 sqlite3 and MCAP) as depth data: written here with rosbags' writers from a
synthetic room, read back through explorer.data.rosbag."""

import numpy as np
import pytest

from explorer.data import rosbag
from explorer.data.rosbag import BagFrames, BagSequence, bag_options, options_path
from explorer.scan import project_scan
from explorer.errors import UserError

from _bags import MOUNT, scene, write_bag

FORMATS = ("ros1", "sqlite3", "mcap")


def _name(fmt):
    return "run.bag" if fmt == "ros1" else f"run_{fmt}"


@pytest.fixture(scope="module")
def sc():
    return scene()


@pytest.fixture(scope="module")
def bags(sc, tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    return {fmt: write_bag(root / _name(fmt), sc, fmt) for fmt in FORMATS}


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """A private cache per test: what an error leaves there is seen."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(folder))
    return folder


def _cached(cache):
    return sorted(p.name for p in (cache / "rosbag").glob("*")) if (cache / "rosbag").is_dir() else []


def _all(frames):
    return [frames[i] for i in range(len(frames))]


def _fails(cache, match, make):
    with pytest.raises(UserError, match=match) as info:
        make()
    assert "\n" not in str(info.value)
    assert _cached(cache) == []
    return str(info.value)


def test_three_formats_give_the_same_frames(sc, bags, cache):
    got = {}
    for fmt, path in bags.items():
        train, val = BagFrames(path, {}, "train"), BagFrames(path, {}, "val")
        assert train.counts == {"images": 14, "duplicate": 0, "no_scan": 0, "no_depth": 0, "paired": 14}
        np.testing.assert_allclose(train.K, sc.K)
        np.testing.assert_allclose(train.T_cam_lidar, sc.T_cam_lidar, atol=1e-6)   # through base_link
        got[fmt] = _all(train) + _all(val)
    ref = got["ros1"]
    assert len(ref) == 13 and [f.name for f in ref][:2] == ["t1700000000.000000000", "t1700000000.100000000"]
    for i, frame in enumerate(ref[:12]):   # train: frames 0..11; val: frame 13 (12 is the gap)
        assert np.array_equal(frame.rgb, sc.rgb[i]) and np.allclose(frame.depth, sc.depth[i])
    for fmt in ("sqlite3", "mcap"):
        for a, b in zip(ref, got[fmt]):
            assert a.name == b.name and np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
            np.testing.assert_allclose(a.scan_points.u, b.scan_points.u, atol=1e-6)
            np.testing.assert_allclose(a.scan_points.z, b.scan_points.z, atol=1e-6)
    # a ROS 2 bag's storage file on its own reads too
    mcap = next(bags["mcap"].glob("*.mcap"))
    assert [f.name for f in _all(BagFrames(mcap, {}, "train"))] == [f.name for f in ref[:12]]


def test_projected_scan_lands_on_the_depth_image(bags):
    for frame in _all(BagFrames(bags["mcap"], {}, "train")):
        p = frame.scan_points
        assert len(p.z) > 30
        u, v = np.round(p.u).astype(int), np.round(p.v).astype(int)
        err = np.abs(frame.depth[v, u] - p.z)
        assert np.median(err) < 0.02 and np.percentile(err, 90) < 0.05


def test_pairing_takes_the_nearest_scan_and_counts_the_skipped(sc, tmp_path, cache):
    path = write_bag(tmp_path / "gaps.bag", sc, scan_offsets=np.full(14, 0.03), skip_scans={3, 4})
    frames = BagFrames(path, {}, "train")
    assert frames.counts["no_scan"] == 2 and frames.counts["paired"] == 12
    names = frames.frame_names()
    assert "t1700000000.300000000" not in names and "t1700000000.400000000" not in names
    for frame in _all(frames):   # each with its own scan (the one 0.03 s later), not a neighbour's
        i = int(round((float(frame.name[1:]) - 1_700_000_000) / 0.1))
        scan = sc.model.scan(sc.ranges[i])
        ref = project_scan(scan, sc.T_cam_lidar, sc.K, (48, 64))
        np.testing.assert_allclose(frame.scan_points.z, ref.z, atol=1e-5)
    # header stamps left 0: the bag's times pair them
    zero = BagFrames(write_bag(tmp_path / "zero.bag", sc, zero_stamps=True), {}, "train")
    assert zero.counts["paired"] == 14 and zero.frame_names()[0] == "t1700000000.002000000"


def test_no_depth_where_the_depth_topic_has_none_nearby(sc, tmp_path):
    path = write_bag(tmp_path / "d.bag", sc, skip_depth={0, 1})
    frames = BagFrames(path, {}, "train")
    assert frames.counts["no_depth"] == 2 and frames.counts["paired"] == 12
    seq = BagSequence(path, {"depth": "none"}, "train")   # depth left out: every frame pairs
    assert seq.counts["paired"] == 14


def test_splits_never_share_a_frame_and_val_comes_last(bags):
    path = bags["sqlite3"]
    train, val = BagFrames(path, {}, "train").frame_names(), BagFrames(path, {}, "val").frame_names()
    assert not set(train) & set(val) and max(train) < min(val)
    assert len(train) + len(val) == 13   # one frame of gap
    s_train, s_val = BagSequence(path, {}, "train"), BagSequence(path, {}, "val")
    assert not set(s_train.frame_names()) & set(s_val.frame_names())
    assert max(s_train.frame_names()) < min(s_val.frame_names())
    sample = s_val[0]
    assert sample.name == s_val.frame_names()[1] and len(sample.frames) == 3
    assert sample.depth.shape == (48, 64) and len(sample.scan_points.z) > 30
    assert sample.poses is not None and s_train[0].poses is None   # validation's motion: the LiDAR's
    assert BagSequence.kind == "frames" and s_train.max_depth == MOUNT["range_max"]
    share = BagFrames(path, {"val": "0.3"}, "val")
    assert len(share) == 4


def test_the_cache_is_read_and_the_bag_is_not(bags, cache, monkeypatch):
    first = BagFrames(bags["ros1"], {}, "train")
    assert len(_cached(cache)) == 1

    def no_reading(*args, **kwargs):
        raise RuntimeError("the bag was read again")

    monkeypatch.setattr(rosbag, "AnyReader", no_reading)
    again = BagFrames(bags["ros1"], {}, "train")
    assert np.array_equal(again[3].rgb, first[3].rgb) and again.frame_names() == first.frame_names()
    with pytest.raises(RuntimeError):   # other options: decoded anew
        BagFrames(bags["ros1"], {"tolerance": "0.02"}, "train")


@pytest.mark.parametrize("image, depth", [("png", "16UC1"), ("bgr8", "32FC1")])
def test_compressed_and_other_encodings(sc, tmp_path, image, depth):
    path = write_bag(tmp_path / "enc", sc, "mcap", image=image, depth=depth)
    frame = BagFrames(path, {}, "train")[5]
    assert np.array_equal(frame.rgb, sc.rgb[5])
    np.testing.assert_allclose(frame.depth, sc.depth[5], atol=6e-4 if depth == "16UC1" else 1e-6)


def test_options_from_the_yaml_beside_the_bag_and_the_command_line(sc, tmp_path):
    folder = write_bag(tmp_path / "run", sc, "sqlite3")
    assert options_path(folder) == tmp_path / "run.yaml"
    assert options_path(tmp_path / "run.mcap") == tmp_path / "run.yaml"
    (tmp_path / "run.yaml").write_text("tolerance: 0.02\nscan: /scan\nlidar:\n  height: 0.1\n")
    opts = bag_options(folder, {"tolerance": "0.03"})
    assert opts.tolerance == 0.03 and opts.scan == "/scan" and opts.mount is not None
    (tmp_path / "run.yaml").write_text("height: 0.1\n")
    with pytest.raises(UserError, match="under lidar:"):
        bag_options(folder, {})
    with pytest.raises(UserError, match="unknown bag option 'topic'.*image, scan"):
        bag_options(tmp_path / "x.bag", {"topic": "/a"})
    with pytest.raises(UserError, match="tolerance"):
        bag_options(tmp_path / "x.bag", {"tolerance": "-1"})


def test_no_depth_topic_for_supervised_data(sc, tmp_path, cache):
    path = write_bag(tmp_path / "nodepth.bag", sc, depth=None)
    with pytest.raises(UserError, match="no depth topic: train self-supervised with rosbag-seq:"):
        BagFrames(path, {}, "train")
    sample = BagSequence(path, {}, "train")[0]
    assert not sample.depth.any()


def test_errors_are_one_line_and_leave_no_cache(sc, bags, tmp_path, cache):
    bag = bags["ros1"]
    msg = _fails(cache, "image=", lambda: BagFrames(bag, {"image": "/nope"}, "train"))
    assert "/camera/color/image_raw" in msg
    two = write_bag(tmp_path / "two.bag", sc, extra=(("/camera/ir/image_raw", "image"),))
    msg = _fails(cache, "image=", lambda: BagFrames(two, {}, "train"))
    assert "/camera/color/image_raw" in msg and "/camera/ir/image_raw" in msg
    assert len(BagFrames(two, {"image": "camera/color/image_raw"}, "train")) == 12   # the leading / optional
    for p in (cache / "rosbag").glob("*"):
        p.unlink()
    late = write_bag(tmp_path / "late.bag", sc, scan_offsets=np.full(14, 0.04))
    msg = _fails(cache, "tolerance=", lambda: BagFrames(late, {"tolerance": "0.03"}, "train"))
    assert "0.04 s" in msg
    bad = write_bag(tmp_path / "cut.bag", sc, cut_ranges=5)
    _fails(cache, "ranges.*imply", lambda: BagFrames(bad, {}, "train"))
    _fails(cache, "not a rigid", lambda: BagFrames(bag, {"T_cam_lidar": "2 0 0 0 0 1 0 0 0 0 1 0"}, "train"))
    _fails(cache, "check the mount", lambda: BagFrames(bag, {"yaw": "180"}, "train"))
    _fails(cache, "no such bag", lambda: BagFrames(tmp_path / "missing.bag", {}, "train"))
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    _fails(cache, "not a readable ROS bag", lambda: BagFrames(tmp_path / "junk.bag", {}, "train"))
    (tmp_path / "empty").mkdir()
    _fails(cache, "metadata.yaml", lambda: BagFrames(tmp_path / "empty", {}, "train"))


def test_no_transform_then_the_mount_beside_the_bag(sc, tmp_path, cache):
    path = write_bag(tmp_path / "notf", sc, "mcap", tf=False)
    msg = _fails(cache, "tf_static", lambda: BagFrames(path, {}, "train"))
    assert "lidar:" in msg and "notf.yaml" in msg
    (tmp_path / "notf.yaml").write_text("lidar:\n  height: 0.05\n  tilt: 2\n")
    frames = BagFrames(path, {}, "train")
    np.testing.assert_allclose(frames.T_cam_lidar, sc.T_cam_lidar, atol=1e-9)
    assert len(frames[0].scan_points.z) > 30


def test_validation_samples_carry_the_motion_the_lidar_measures_and_it_scores_depth(bags):
    """The camera drives 5 cm a frame toward the far wall: the scans say so, and with that motion the
    recorded depth explains the neighbouring frames better than the same depth off in scale."""
    import torch
    from explorer.data import open_dataset
    from explorer.training.selfsup import photometric_score
    val = open_dataset(f"rosbag-seq:{bags['mcap']}", "val", (48, 64))
    train = BagSequence(bags["mcap"], {}, "train")
    assert train.poses is None   # training learns its poses; only validation is scored with these
    batch = {k: torch.stack([torch.as_tensor(val[i][k]) for i in range(len(val))])
             for k in ("image", "sources", "K", "pose", "depth")}
    assert all(bool(val[i]["pose_known"]) for i in range(len(val)))
    # target to previous frame: a point 5 cm further away; to the next one: 5 cm nearer
    assert np.allclose(batch["pose"][:, 0, 2, 3], 0.05, atol=0.005)
    assert np.allclose(batch["pose"][:, 1, 2, 3], -0.05, atol=0.005)
    depth = batch["depth"]
    true = photometric_score(depth, batch)
    for wrong in (depth * 0.5, depth * 2.0, torch.full_like(depth, float(depth.mean()))):
        assert bool((photometric_score(wrong, batch) > true).all())
