import json
import os
import signal
import subprocess
import sys
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from explorer.errors import UserError
from explorer.files import MAX_TEXT_BYTES, read_json, read_yaml, write_atomically, write_json

def _reads_or_says_one_line(read, path) -> None:
    """``read(path)`` returns, or raises the package's user error in one line naming the file."""
    try:
        read(path)
    except UserError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)


FILE_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@FILE_SETTINGS
@given(st.binary(max_size=2000))
def test_any_bytes_parse_as_yaml_or_are_one_user_error(tmp_path, raw):
    path = tmp_path / "x.yaml"
    path.write_bytes(raw)
    _reads_or_says_one_line(read_yaml, path)


@FILE_SETTINGS
@given(st.text(alphabet="ab:-&*[]{},'\"\n #!x1", max_size=300))
def test_any_yaml_like_text_parses_or_is_one_user_error(tmp_path, text):
    path = tmp_path / "x.yaml"
    path.write_text(text)
    _reads_or_says_one_line(read_yaml, path)


@FILE_SETTINGS
@given(st.text(max_size=300))
def test_any_text_parses_as_json_or_is_one_user_error(tmp_path, text):
    path = tmp_path / "x.json"
    path.write_text(text)
    _reads_or_says_one_line(read_json, path)


def test_binary_folders_missing_and_huge_files_are_named(tmp_path):
    (tmp_path / "bin").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(UserError, match="binary"):
        read_yaml(tmp_path / "bin")
    with pytest.raises(UserError, match="folder"):
        read_yaml(tmp_path)
    with pytest.raises(UserError, match="no such file"):
        read_yaml(tmp_path / "nope.yaml")
    (tmp_path / "big.yaml").write_bytes(b"a" * (MAX_TEXT_BYTES + 1))
    with pytest.raises(UserError, match="larger"):
        read_yaml(tmp_path / "big.yaml")
    (tmp_path / "nan.json").write_text('{"ms": NaN}')
    with pytest.raises(UserError, match="NaN"):
        read_json(tmp_path / "nan.json")


def test_write_atomically_replaces_whole_and_leaves_no_scratch(tmp_path):
    target = tmp_path / "out.json"
    write_json(target, {"a": 1})
    write_atomically(target, "new")
    assert target.read_text() == "new" and os.listdir(tmp_path) == ["out.json"]
    assert json.loads(write_json(target, [1, 2]).read_text()) == [1, 2]


@pytest.mark.parametrize("stop", [RuntimeError, KeyboardInterrupt])
def test_a_file_written_by_name_replaces_whole_or_leaves_the_old_one(tmp_path, stop):
    """``replacing_file``, for writers that open the file by name (HDF5): the target changes only when
    the block ends; an error or Ctrl-C midway leaves the old file and no scratch."""
    from explorer.files import current_umask, replacing_file
    target = tmp_path / "cache.h5"
    target.write_bytes(b"old")
    with pytest.raises(stop):
        with replacing_file(target) as scratch:
            assert scratch.parent == tmp_path and scratch.is_file() and scratch != target
            scratch.write_bytes(b"half")
            raise stop()
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["cache.h5"]
    with replacing_file(target) as scratch:
        scratch.write_bytes(b"new")
        assert target.read_bytes() == b"old"   # not yet
    assert target.read_bytes() == b"new" and os.listdir(tmp_path) == ["cache.h5"]
    assert target.stat().st_mode & 0o777 == 0o666 & ~current_umask()


@pytest.mark.slow
def test_a_writer_killed_midway_leaves_the_old_file(tmp_path):
    """A child writes a large file over and over; killed at random moments, the target always holds
    one whole version."""
    target = tmp_path / "data.json"
    write_json(target, {"version": -1, "payload": "x"})
    code = ("import sys; from explorer.files import write_json\n"
            "i = 0\n"
            "while True:\n"
            "    write_json(sys.argv[1], {'version': i, 'payload': 'y' * 2_000_000}); i += 1\n")
    for delay in (0.3, 0.5, 0.8):
        child = subprocess.Popen([sys.executable, "-c", code, str(target)])
        time.sleep(delay)
        child.send_signal(signal.SIGKILL)
        child.wait()
        data = json.loads(target.read_text())
        assert data["payload"] in ("x", "y" * 2_000_000)


def test_a_few_aliases_as_yaml_dump_writes_them_are_read(tmp_path):
    shared = [1, 2, 3]
    path = tmp_path / "x.yaml"
    import yaml
    path.write_text(yaml.safe_dump({"a": shared, "b": shared}))
    assert "&id" in path.read_text() and read_yaml(path) == {"a": [1, 2, 3], "b": [1, 2, 3]}


def test_a_key_given_twice_in_any_users_yaml_is_refused_with_both_lines(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("depth: /depth\nimage: /camera\ndepth: /depth2\n")
    with pytest.raises(UserError) as err:
        read_yaml(path)
    assert str(err.value) == f"{path}: the key 'depth' is given twice (lines 1 and 3); keep one"
    path.write_text("rates:\n  conv: 1\n  pointwise: 2\n  conv: 3\n")
    with pytest.raises(UserError, match=r"'conv' is given twice \(lines 2 and 4\)"):
        read_yaml(path)
    # the same key in two mappings, and a merge key that a mapping overrides, are YAML as written
    path.write_text("a: {x: 1}\nb: {x: 2}\nbase: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n")
    assert read_yaml(path)["c"] == {"x": 3, "y": 2} and read_yaml(path)["b"] == {"x": 2}


def test_a_16_bit_grey_frame_is_scaled_not_clipped_to_white(tmp_path):
    """A 16-bit camera frame (mono industrial cameras write them) keeps its contrast as RGB."""
    import numpy as np
    from PIL import Image

    from explorer.files import read_image
    ramp = np.tile(np.linspace(0, 65535, 64).astype(np.uint16), (8, 1))
    Image.fromarray(ramp).save(tmp_path / "f.png")
    rgb = read_image(tmp_path / "f.png", "RGB")
    assert rgb.shape == (8, 64, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0, 0] == 0 and rgb[0, -1, 0] == 255 and (rgb[0, 1:, 0] >= rgb[0, :-1, 0]).all()
    assert (rgb == 255).mean() < 0.05                                  # not clipped to white


def test_a_writable_check_that_may_not_keep_makes_nothing_even_when_run_at_once(tmp_path):
    """Commands refused at the same moment (a missing folder probed by each) leave the folder as they
    found it: none makes the folder, so none can leave it behind for another's files."""
    from concurrent.futures import ThreadPoolExecutor

    from explorer.files import check_writable_folder
    target = tmp_path / "reports" / "checkpoints"
    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(lambda _: check_writable_folder(target, "checkpoint", "fix", keep=False), range(64)))
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "afile").write_text("x")
    with pytest.raises(UserError, match="afile: is a file"):
        check_writable_folder(tmp_path / "afile" / "sub", "checkpoint", "fix", keep=False)
    kept = check_writable_folder(target, "checkpoint", "fix")
    assert kept.is_dir() and list(kept.iterdir()) == []


def test_an_output_that_is_one_of_the_inputs_is_refused(tmp_path):
    from explorer.files import refuse_overwriting_inputs
    image = tmp_path / "frame.png"
    image.write_bytes(b"mine")
    (tmp_path / "link.png").symlink_to(image)
    for out in (image, tmp_path / "link.png", tmp_path / "." / "frame.png"):
        with pytest.raises(UserError, match="is the file given to --image; write the output to another file"):
            refuse_overwriting_inputs(out, "--out", {"--image": image, "--scan": None})
    refuse_overwriting_inputs(tmp_path / "depth.png", "--out", {"--image": image})   # a new file: fine
    assert image.read_bytes() == b"mine"
