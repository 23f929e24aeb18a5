"""A bag refused is refused before its cache is written: the cache folder (``ANYTIME_EXPLORER_CACHE``)
is left exactly as it was, no .h5, no scratch, no ``rosbag/`` folder it did not have; a good bag
still caches once and is read from the cache after."""

import os

import numpy as np
import pytest

from explorer.cli import main
from explorer.data import open_dataset, rosbag
from explorer.data.rosbag import BagFrames, BagSequence
from explorer.errors import UserError

from _bags import scene, write_bag


@pytest.fixture(scope="module")
def sc():
    return scene()


@pytest.fixture(scope="module")
def nodepth(sc, tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bags") / "nodepth.bag", sc, depth=None)


@pytest.fixture(scope="module")
def good(sc, tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bags") / "good.bag", sc)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    folder.mkdir()
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(folder))
    return folder


def _listing(folder):
    """Every file and folder under ``folder`` (hidden scratch included), with the files' sizes."""
    return sorted((str(p.relative_to(folder)), p.stat().st_size if p.is_file() else None)
                  for p in folder.rglob("*"))


def _refused(cache, match, make):
    before = _listing(cache)
    with pytest.raises(UserError, match=match) as info:
        make()
    assert "\n" not in str(info.value)
    assert _listing(cache) == before
    return str(info.value)


def test_no_depth_topic_refused_before_the_cache_is_written(nodepth, cache):
    msg = _refused(cache, "no depth topic: train self-supervised with rosbag-seq:",
                   lambda: open_dataset("rosbag:" + str(nodepth), "val", (32, 32)))
    assert str(nodepth) in msg
    assert not (cache / "rosbag").exists()
    # a rosbag/ folder there before stays, and stays as it was
    (cache / "rosbag").mkdir()
    (cache / "rosbag" / "other.h5").write_bytes(b"someone else's cache")
    _refused(cache, "no depth topic", lambda: BagFrames(nodepth, {}, "train"))
    assert (cache / "rosbag" / "other.h5").read_bytes() == b"someone else's cache"


def test_no_depth_topic_refused_by_the_cli(nodepth, cache, capsys):
    before = _listing(cache)
    assert main(["data", "inspect", "--data", f"rosbag:{nodepth}"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no depth topic: train self-supervised with rosbag-seq:" in err and "\n" not in err
    assert _listing(cache) == before


def test_the_self_supervised_reading_still_caches_then_supervised_is_refused(nodepth, cache):
    seq = BagSequence(nodepth, {}, "train")
    assert len(seq) > 0 and seq.cache.is_file()
    before = _listing(cache)
    assert len([p for p in before if p[0].endswith(".h5")]) == 1
    _refused(cache, "no depth topic", lambda: BagFrames(nodepth, {}, "train"))   # from the cache
    assert _listing(cache) == before


def test_too_few_frames_refused_before_the_cache_is_written(sc, tmp_path, cache):
    short = write_bag(tmp_path / "short.bag", sc, skip_scans=set(range(2, 14)))   # 2 frames pair
    _refused(cache, "a sequence needs at least 3", lambda: BagSequence(short, {}, "train"))
    _refused(cache, "too few", lambda: BagFrames(short, {}, "train"))
    assert not (cache / "rosbag").exists()


def test_a_frame_that_fails_to_decode_leaves_nothing(good, cache, monkeypatch):
    """A refusal midway through writing the cache: no scratch file, no folder made for it."""
    root = cache / "new" / "deeper"   # the cache folder itself missing: made, then removed again
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(root))
    calls = []

    def bad_image(msg, msgtype, at):
        calls.append(at)
        if len(calls) == 3:
            raise UserError(f"{at}: an image does not decode")
        return real(msg, msgtype, at)

    real = rosbag._decode_image
    monkeypatch.setattr(rosbag, "_decode_image", bad_image)
    _refused(cache, "does not decode", lambda: BagFrames(good, {}, "train"))
    assert len(calls) == 3 and not (cache / "new").exists()
    # the same with the cache folder there before: it stays, empty
    root.mkdir(parents=True)
    calls.clear()
    _refused(cache, "does not decode", lambda: BagFrames(good, {}, "train"))
    assert root.is_dir() and not any(root.iterdir())


def test_a_good_bag_still_caches_and_reads_back(sc, good, cache, tmp_path, monkeypatch):
    bag = tmp_path / "run.bag"
    bag.write_bytes(good.read_bytes())
    first = BagFrames(bag, {}, "train")
    files = list((cache / "rosbag").iterdir())
    assert [p.suffix for p in files] == [".h5"] and first.cache == files[0]
    assert np.array_equal(first[0].rgb, sc.rgb[0])

    real = rosbag.AnyReader

    def no_reading(*args, **kwargs):
        raise RuntimeError("the bag was read again")

    monkeypatch.setattr(rosbag, "AnyReader", no_reading)
    again = BagFrames(bag, {}, "val")   # from the cache
    assert again.cache == first.cache and len(again) == 1
    assert np.array_equal(again[0].rgb, sc.rgb[13])
    assert BagSequence(bag, {}, "train").cache == first.cache   # one cache for both readings
    # a bag replaced at the same path is decoded anew, into a cache of its own
    bag.write_bytes(good.read_bytes())
    os.utime(bag, ns=(1, 1))
    with pytest.raises(RuntimeError, match="read again"):
        BagFrames(bag, {}, "train")
    monkeypatch.setattr(rosbag, "AnyReader", real)
    replaced = BagFrames(bag, {}, "train")
    assert replaced.cache != first.cache and replaced.cache.is_file()
    assert replaced.frame_names() == first.frame_names()


def test_a_mistaken_bag_path_or_topic_is_one_line_that_says_what_to_give(good, sc, cache, tmp_path):
    _refused(cache, r"is named as the depth, and no other topic is the camera's image; name the depth topic",
             lambda: open_dataset(f"rosbag:{good},depth=/camera/color/image_raw", "val", (32, 32)))
    folder = write_bag(tmp_path / "r2", sc, fmt="sqlite3")
    _refused(cache, "a YAML file, not a bag: give the ROS 2 bag's folder",
             lambda: open_dataset(f"rosbag:{folder / 'metadata.yaml'}", "val", (32, 32)))
    copy = tmp_path / "copy.bag"
    copy.write_bytes(good.read_bytes())
    (tmp_path / "copy.yaml").mkdir()
    _refused(cache, "copy.yaml: is a folder where the bag's options file goes",
             lambda: open_dataset(f"rosbag:{copy}", "val", (32, 32)))
