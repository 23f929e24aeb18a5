"""Cleanup (issue 89): what a command removes is only what it made. Scratch that a killed writer left
(named with its pid) is removed by the next writer, a live process's is kept, and a user's own files and
folders named like scratch (``results.tmpNNN``) beside any command's output survive every command; a
writer that fails (an error, Ctrl-C, a full disk) removes its own scratch and leaves the old file."""

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from _faults import WRITERS, dead_pid, writer
from _faults import searched_study_fixture, trained_checkpoint_fixture  # noqa: F401  (fixtures)


def test_scratch_of_dead_processes_is_removed_and_live_ones_kept(tmp_path):
    from explorer.files import remove_dead_scratch
    dead, alive = dead_pid(), os.getpid()
    (tmp_path / f"synthetic-x.tmp{dead}").write_bytes(b"half")
    (tmp_path / f".model.tmp{dead}").mkdir()
    (tmp_path / f"synthetic-y.tmp{alive}").write_bytes(b"being written")
    (tmp_path / "synthetic-z.h5").write_bytes(b"whole")
    removed = remove_dead_scratch(tmp_path)
    assert sorted(p.name for p in removed) == sorted([f"synthetic-x.tmp{dead}", f".model.tmp{dead}"])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f"synthetic-y.tmp{alive}", "synthetic-z.h5"])


def test_a_process_ended_by_sigterm_removes_its_own_scratch_folders_and_only_those(tmp_path):
    """What a signal between making a folder and entering the block that removes it would leave."""
    from explorer.files import remove_own_scratch
    mine, other = tmp_path / f"explorer-{os.getpid()}-int8-abc", tmp_path / f"explorer-{dead_pid()}-export-abc"
    for folder in (mine, other):
        (folder / "sub").mkdir(parents=True)
    (tmp_path / f"explorer-{os.getpid()}-note.txt").write_text("a file, not a scratch folder")
    remove_own_scratch(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other.name, f"explorer-{os.getpid()}-note.txt"])


def test_a_scratch_folder_of_a_dead_process_is_removed_when_the_next_is_made(tmp_path, monkeypatch):
    """kill -9 leaves a scratch folder behind (nothing can catch it): the next one made removes it, and
    leaves a live process's and every folder not named as scratch."""
    import tempfile
    from pathlib import Path

    from explorer.files import scratch_dir
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead, alive = dead_pid(), os.getppid()
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


def test_a_checkpoints_cleanup_touches_only_its_own_scratch(tmp_path):
    from explorer.files import remove_dead_scratch
    dead = dead_pid()
    mine = [f"ck.pt.tmp{dead}", f".ck.pt.ab12.tmp{dead}"]
    theirs = [f"results.tmp{dead}", f"run.tmp{dead + 1}", f"ck.tmp{dead}", f"other.pt.tmp{dead}"]
    for name in mine + theirs:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / f"exp.tmp{dead}").mkdir()
    removed = remove_dead_scratch(tmp_path, only_for=tmp_path / "ck.pt")
    assert sorted(p.name for p in removed) == sorted(mine)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(theirs + [f"exp.tmp{dead}"])


def test_train_out_keeps_the_users_files_beside_the_checkpoint(tmp_path, run_cli):
    dead = dead_pid()
    out = tmp_path / "out"
    out.mkdir()
    (out / f"results.tmp{dead}").write_text("mine")
    (out / f"run.tmp{dead}").mkdir()
    code, _, err = run_cli("train", "paper", "--data", "synthetic:48:16", "--steps", "1", "--batch-size", "2",
                           "--train-size", "32x32", "--out", out / "ck.pt")
    assert code == 0, err
    assert (out / f"results.tmp{dead}").read_text() == "mine" and (out / f"run.tmp{dead}").is_dir()
    assert (out / "ck.pt").is_file()


def test_a_checkpoint_save_cleans_what_a_killed_save_left(tmp_path):
    from explorer.model import build_network
    from explorer.space import paper_candidate
    from explorer.training.train import TrainConfig, save_checkpoint
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    (tmp_path / f"c.pt.tmp{child.pid}").write_bytes(b"half a checkpoint")
    save_checkpoint(tmp_path / "c.pt", build_network(paper_candidate()), TrainConfig(), 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"]


def _plant(folder: Path) -> dict[str, str | None]:
    """Files (their text) and folders (None) of the user's own beside an output, named as scratch is: by a
    dead process's id, a live one's, the old report's scratch name, a part file."""
    dead = dead_pid()
    planted = {f"results.tmp{dead}": "mine", f"notes.txt.tmp{os.getpid()}": "mine", "report.tmp": "mine",
               f"model.tmp{dead}": "mine", "bundle.tar.part": "mine", f"run.tmp{dead}": None, f"exp.tmp{dead}": None}
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in planted.items():
        (folder / name).mkdir() if text is None else (folder / name).write_text(text)
    return planted


@pytest.mark.parametrize("command", list(WRITERS))
def test_the_users_files_named_like_scratch_survive_every_command(tmp_path, run_cli, command, searched_study,
                                                                   trained_checkpoint):
    out = tmp_path / "out"
    if command == "search":    # the study's own folder: its journal, its lock, its report
        shutil.copytree(searched_study, out)
    planted = _plant(out / "cc" if command == "search" else out)
    code, _, err = run_cli(*writer(command, out, trained_checkpoint, searched_study))
    assert code == 0, err
    folder = out / "cc" if command == "search" else out
    for name, text in planted.items():
        assert (folder / name).is_dir() if text is None else (folder / name).read_text() == text, name
    assert (out / WRITERS[command][1]).exists()


def _fails_at(stop: str, monkeypatch) -> None:
    """Makes the writer fail: in its block (an error, Ctrl-C), or when it flushes to a full disk."""
    if stop == "full disk":
        monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left")))


def _write(kind: str, target: Path, stop: str):
    """Writes ``target`` anew with the writer ``kind``, stopped by ``stop``."""
    from explorer import files

    def body(write):
        write()
        if stop == "error":
            raise RuntimeError("stopped")
        if stop == "Ctrl-C":
            raise KeyboardInterrupt

    if kind == "writing_atomically":
        with files.writing_atomically(target) as f:
            body(lambda: f.write(b"new"))
    elif kind == "replacing_file":
        with files.replacing_file(target) as scratch:
            body(lambda: scratch.write_bytes(b"new"))
    elif kind == "writing_hdf5":
        with files.writing_hdf5(target) as out:
            body(lambda: out.file.create_dataset("x", data=list(range(1000))))
    elif kind == "replacing_folder":
        with files.replacing_folder(target, "marker") as scratch:
            body(lambda: files.write_atomically(scratch / "marker", "new"))   # as an export writes its manifest
    else:   # a checkpoint, stopped while torch writes it
        import torch

        from explorer.model import build_network
        from explorer.space import paper_candidate
        from explorer.training.train import TrainConfig, save_checkpoint
        real = torch.save

        def save(obj, f, *args, **kwargs):
            if stop == "full disk":
                return real(obj, f, *args, **kwargs)
            f.write(b"half a checkpoint")
            body(lambda: None)

        torch.save = save
        try:
            save_checkpoint(target, build_network(paper_candidate()), TrainConfig(), 1)
        finally:
            torch.save = real


@pytest.mark.parametrize("stop", ["error", "Ctrl-C", "full disk"])
@pytest.mark.parametrize("kind", ["writing_atomically", "replacing_file", "writing_hdf5", "replacing_folder",
                                  "checkpoint"])
def test_a_writer_that_fails_leaves_the_old_file_and_no_scratch(tmp_path, monkeypatch, kind, stop):
    target = tmp_path / ("model" if kind == "replacing_folder" else "target")
    if kind == "replacing_folder":
        target.mkdir()
        (target / "marker").write_text("old")
    else:
        target.write_text("old")
    _fails_at(stop, monkeypatch)
    with pytest.raises((RuntimeError, KeyboardInterrupt, OSError)) as caught:
        _write(kind, target, stop)
    if stop == "full disk":
        from explorer.errors import refused_write
        refused = refused_write(caught.value)
        assert refused is not None and refused.filename == str(target)   # the file, not its scratch
    assert [p.name for p in tmp_path.iterdir()] == [target.name]
    assert (target / "marker" if kind == "replacing_folder" else target).read_text() == "old"
