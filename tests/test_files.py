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


def test_an_alias_bomb_is_refused_at_once(tmp_path):
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    start = time.monotonic()
    with pytest.raises(UserError, match="aliases expand"):
        read_yaml(path)
    assert time.monotonic() - start < 1.0


@pytest.mark.parametrize("text", ["x: " + "[" * 5000 + "]" * 5000, "{a: " * 3000 + "1" + "}" * 3000,
                                  "- " * 2000 + "1"])
def test_deep_nesting_is_one_line_not_a_recursion_error(tmp_path, text):
    path = tmp_path / "deep.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match="nest more than 100 deep") as caught:
        read_yaml(path)
    assert "\n" not in str(caught.value)
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(UserError, match="nested too deep"):
        read_json(tmp_path / "deep.json")


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


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_scratch_of_dead_processes_is_removed_and_live_ones_kept(tmp_path):
    from explorer.files import remove_dead_scratch
    dead, alive = _dead_pid(), os.getpid()
    (tmp_path / f"synthetic-x.tmp{dead}").write_bytes(b"half")
    (tmp_path / f".model.tmp{dead}").mkdir()
    (tmp_path / f"synthetic-y.tmp{alive}").write_bytes(b"being written")
    (tmp_path / "synthetic-z.h5").write_bytes(b"whole")
    removed = remove_dead_scratch(tmp_path)
    assert sorted(p.name for p in removed) == sorted([f"synthetic-x.tmp{dead}", f".model.tmp{dead}"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f"synthetic-y.tmp{alive}", "synthetic-z.h5"])


@pytest.mark.slow
def test_a_generation_stopped_by_sigterm_leaves_nothing_after_the_next_start(tmp_path):
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(tmp_path)}
    code = "from explorer.data import open_dataset; open_dataset('synthetic:600:100', 'train', (64, 64))"
    child = subprocess.Popen([sys.executable, "-c", code], env=env)
    deadline = time.time() + 120
    while time.time() < deadline and not any(".tmp" in p.name for p in tmp_path.iterdir()):
        time.sleep(0.1)
    child.send_signal(signal.SIGTERM)
    child.wait()
    subprocess.run([sys.executable, "-c", code.replace("600:100", "8:4")], env=env, check=True)
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_a_scratch_folder_of_a_dead_process_is_removed_when_the_next_is_made(tmp_path, monkeypatch):
    """kill -9 leaves a scratch folder behind (nothing can catch it): the next one made removes it, and
    leaves a live process's and every folder not named as scratch."""
    import tempfile
    from pathlib import Path

    from explorer.files import scratch_dir
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead, alive = _dead_pid(), os.getppid()
    stale = tmp_path / f"explorer-{dead}-calibrate-k2j4h0ns"
    (stale / "bundle").mkdir(parents=True)
    (stale / "bundle" / "L000-conv.onnx").write_bytes(b"graph" * 1000)
    kept = [f"explorer-{alive}-export-1q2w3e4r", f"explorer-{dead}", "explorer-cache", f"other-{dead}-x"]
    for name in kept:
        (tmp_path / name).mkdir()
    with scratch_dir("calibrate") as tmp:
        assert Path(tmp).parent == tmp_path and Path(tmp).name.startswith(f"explorer-{os.getpid()}-calibrate-")
        assert not stale.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept)


SCRATCH_THEN_WAIT = ("import sys, time\n"
                     "from explorer.files import scratch_dir, sigterm_unwinds\n"
                     "with sigterm_unwinds(), scratch_dir('calibrate') as tmp:\n"
                     "    open(tmp + '/results.json', 'w').write('{}')\n"
                     "    print(tmp, flush=True)\n"
                     "    time.sleep(120)\n")


def test_sigterm_unwinds_and_leaves_no_scratch_folder(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", SCRATCH_THEN_WAIT], env={**os.environ, "TMPDIR": str(tmp_path)},
                             stdout=subprocess.PIPE, text=True)
    folder = child.stdout.readline().strip()
    assert os.path.isdir(folder) and os.path.dirname(folder) == str(tmp_path)
    child.send_signal(signal.SIGTERM)
    assert child.wait(timeout=60) == 128 + signal.SIGTERM
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_a_calibration_stopped_by_sigterm_leaves_nothing_in_the_temporary_folder(tmp_path):
    """`explorer calibrate`, stopped while it exports its graphs into its scratch folder: the folder
    goes with it."""
    env = {**os.environ, "TMPDIR": str(tmp_path / "tmp"), "OMP_NUM_THREADS": "1"}
    (tmp_path / "tmp").mkdir()
    with open(tmp_path / "stderr", "w") as err:
        child = subprocess.Popen([sys.executable, "-m", "explorer", "calibrate", "--quick", "--out",
                                  str(tmp_path / "p.yaml")], env=env, stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.time() + 120
    while (time.time() < deadline and child.poll() is None
           and not any((tmp_path / "tmp").glob(f"explorer-{child.pid}-calibrate-*/bundle"))):
        time.sleep(0.1)
    assert child.poll() is None, (tmp_path / "stderr").read_text()[-2000:]
    child.send_signal(signal.SIGTERM)
    assert child.wait(timeout=60) == 128 + signal.SIGTERM
    # (onnxruntime keeps a small file of its own there)
    assert not list((tmp_path / "tmp").glob("explorer-*")) and not (tmp_path / "p.yaml").exists()


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


def test_a_checkpoints_cleanup_touches_only_its_own_scratch(tmp_path):
    from explorer.files import remove_dead_scratch
    dead = _dead_pid()
    mine = [f"ck.pt.tmp{dead}", f".ck.pt.ab12.tmp{dead}"]
    theirs = [f"results.tmp{dead}", f"run.tmp{dead + 1}", f"ck.tmp{dead}", f"other.pt.tmp{dead}"]
    for name in mine + theirs:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / f"exp.tmp{dead}").mkdir()
    removed = remove_dead_scratch(tmp_path, only_for=tmp_path / "ck.pt")
    assert sorted(p.name for p in removed) == sorted(mine)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(theirs + [f"exp.tmp{dead}"])


def test_train_out_keeps_the_users_files_beside_the_checkpoint(tmp_path, run_cli):
    dead = _dead_pid()
    out = tmp_path / "out"
    out.mkdir()
    (out / f"results.tmp{dead}").write_text("mine")
    (out / f"run.tmp{dead}").mkdir()
    code, _, err = run_cli("train", "paper", "--data", "synthetic:48:16", "--steps", "1", "--batch-size", "2",
                           "--train-size", "32x32", "--out", out / "ck.pt")
    assert code == 0, err
    assert (out / f"results.tmp{dead}").read_text() == "mine" and (out / f"run.tmp{dead}").is_dir()
    assert (out / "ck.pt").is_file()
