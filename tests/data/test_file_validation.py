"""Intrinsics, poses and images a user hands in are checked before any tensor is built: whatever the
file holds, it parses or it is one UserError line."""

import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from explorer.data.readers import read_image
from explorer.data.sequence_readers import read_intrinsics, read_poses
from explorer.errors import UserError

SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6))
WORDS = st.one_of(NUMBERS.map(str), st.sampled_from(["nan", "inf", "-inf", "x", "1e400", ",", "", "0"]))


@SETTINGS
@given(st.lists(WORDS, max_size=12))
def test_any_intrinsics_file_is_a_camera_matrix_or_one_user_error(tmp_path, words):
    path = tmp_path / "intrinsics.txt"
    path.write_text(" ".join(words))
    try:
        K = read_intrinsics(path)
    except UserError as exc:
        assert "\n" not in str(exc)
        return
    assert K.shape == (3, 3) and np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0
    np.linalg.inv(K)   # a camera matrix is invertible


@pytest.mark.parametrize("text, why", [("nan 0 32 24", "finite"), ("0 0 32 24", "positive"),
                                       ("100 100 32 24 1", "5 numbers"), ("a b c d", "numbers"),
                                       ("1 0 0 0 1 0 0 0 0", "camera matrix")])
def test_bad_intrinsics_say_what_is_wrong(tmp_path, text, why):
    path = tmp_path / "intrinsics.txt"
    path.write_text(text)
    with pytest.raises(UserError, match=why):
        read_intrinsics(path)


@SETTINGS
@given(st.lists(st.lists(WORDS, min_size=12, max_size=12), min_size=3, max_size=3))
def test_any_poses_file_is_finite_poses_or_one_user_error(tmp_path, rows):
    path = tmp_path / "poses.txt"
    path.write_text("\n".join(" ".join(r) for r in rows))
    try:
        poses = read_poses(path, 3)
    except UserError as exc:
        assert "\n" not in str(exc)
        return
    assert all(np.isfinite(p).all() and abs(np.linalg.det(p[:3, :3])) > 0 for p in poses)


def test_text_in_poses_names_the_line(tmp_path):
    path = tmp_path / "poses.txt"
    good = " ".join(str(x) for x in np.eye(4)[:3].reshape(-1))
    path.write_text("\n".join([good, good.replace("1.0", "one", 1), good]))
    with pytest.raises(UserError, match="line 2"):
        read_poses(path, 3)


def test_an_image_claiming_too_many_pixels_is_refused(tmp_path):
    path = tmp_path / "bomb.png"
    Image.new("L", (64, 64)).save(path)   # a small image whose header then claims 40000x40000
    raw = bytearray(path.read_bytes())
    raw[16:24] = (40000).to_bytes(4, "big") + (40000).to_bytes(4, "big")   # IHDR width, height
    raw[29:33] = zlib.crc32(bytes(raw[12:29])).to_bytes(4, "big")          # the chunk's CRC again
    path.write_bytes(bytes(raw))
    with pytest.raises(UserError, match="more pixels"):
        read_image(path)


def test_a_binary_file_is_not_an_image(tmp_path):
    path = tmp_path / "x.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(UserError, match="unreadable image"):
        read_image(path)
