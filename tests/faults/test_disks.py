"""Disks (issue 89): every place a command writes is checked before its work: a file where a folder goes,
a folder nobody can write (even root: /proc, a read-only mount), is one line, exit 2, with nothing
written. A disk that fills while a command writes (search, export, supernet train, train, report, a
data cache) is one line saying what was kept, exit 2, no traceback, no scratch left, nothing stored lost;
HDF5 never sees the failed write (it crashed the process at exit, a segmentation fault)."""

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import optuna
import pytest

from explorer.errors import UserError
from conftest import TINY_DATA
from _faults import (WRITERS, disk_full_under, explorer, fast_search, files, on_full_disk, read_only, says_one_line,
                     scratch, writer)
from _faults import searched_study_fixture, trained_checkpoint_fixture  # noqa: F401  (fixtures)


def _plain_study(tmp_path) -> Path:
    journal = tmp_path / "s.log"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    optuna.create_study(study_name="s", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    return journal


@pytest.mark.parametrize("out, says", [("existing.html", "is a file, not a folder for the report"),
                                       ("/proc/r", "cannot write the report there")])
def test_report_out_where_a_report_cannot_go_is_one_line(tmp_path, run_cli, out, says):
    journal = _plain_study(tmp_path)
    (tmp_path / "existing.html").write_text("mine")
    before = sorted(p.name for p in tmp_path.iterdir()), journal.read_bytes()
    code, _, err = run_cli("report", "--study", "s", "--storage", f"journal:{journal}",
                           "--out", out if out.startswith("/") else tmp_path / out)
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert (sorted(p.name for p in tmp_path.iterdir()), journal.read_bytes()) == before
    assert (tmp_path / "existing.html").read_text() == "mine"


@pytest.mark.parametrize("out", ["/proc/x.png", "/proc/nope/x.npy"])
def test_a_depth_map_that_cannot_be_written_is_refused_before_the_model_runs(out):
    from explorer.deploy.runtime import check_depth_out
    with pytest.raises(UserError, match="give --out a path you can write") as caught:
        check_depth_out(Path(out))
    assert "\n" not in str(caught.value)


def test_a_search_in_a_folder_that_cannot_be_written_is_one_line(run_cli):
    code, _, err = run_cli("search", "--space", "tiny", "--trials", "1", "--storage", "journal:/proc/j.log")
    assert code == 2 and "give --reports or --storage a folder you can write" in err, err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", [["train", "paper", "--steps", "1", "--out", "/proc/x/ck.pt"],
                                     ["supernet", "train", "--space", "tiny", "--steps", "1",
                                      "--out", "/proc/x/sn.pt"]])
def test_training_onto_a_folder_that_cannot_be_written_is_one_line_before_any_training(run_cli, monkeypatch,
                                                                                       command):
    import explorer.data
    import explorer.supernet
    import explorer.training.train
    monkeypatch.setattr(explorer.data, "open_dataset", _no_work)
    monkeypatch.setattr(explorer.training.train, "train", _no_work)
    monkeypatch.setattr(explorer.supernet, "train_supernet", _no_work)
    code, _, err = run_cli(*command)
    assert code == 2 and "/proc/x: cannot write the" in err and "give --out" in err, err
    assert len(err.strip().splitlines()) == 1


# -- a disk that fills while the command writes -------------------------------------------------------

#: what each command's line says it kept, and what it wrote before its write failed
FULL_DISK_SAYS = {
    "train": "no checkpoint was saved yet: run the same command again",
    "supernet train": "no supernet was saved yet: run the same command again",
    "export": "nothing is left half-written and what was saved before is kept",
    "report": "nothing is left half-written and what was saved before is kept",
    "search": "study 'cc' keeps its 1 finished trial(s) in",
}


@pytest.mark.parametrize("command", list(FULL_DISK_SAYS))
def test_a_disk_that_fills_is_one_line_saying_what_was_kept(tmp_path, run_cli, monkeypatch, command, searched_study,
                                                              trained_checkpoint):
    out = tmp_path / "out"
    if command == "search":
        shutil.copytree(searched_study, out)
    elif command == "export":   # an export there already: kept whole
        assert run_cli(*writer("export", out, trained_checkpoint))[0] == 0
    elif command == "report":
        out.mkdir()
        (out / "report.html").write_text("the report before")
    before = {p: (out / p).read_bytes() for p in files(out) if (out / p).is_file()} if out.exists() else {}
    disk_full_under(monkeypatch, out)
    code, _, err = run_cli(*writer(command, out, trained_checkpoint, searched_study))
    line = says_one_line(err)
    assert code == 2 and "cannot write it (no space left on device): free space on that disk" in line, line
    assert FULL_DISK_SAYS[command] in line, line
    assert str(out / WRITERS[command][1]) in line or (command == "search" and str(out / "cc" / "journal.log") in line)
    assert not scratch(out), files(out)
    if command == "search":   # the finished trial is still there, and the study opens
        monkeypatch.undo()
        from explorer.study.storage import open_storage
        journal = f"journal:{out / 'cc' / 'journal.log'}"
        study = optuna.load_study(study_name="cc", storage=open_storage(journal, "cc", create=False))
        assert sum(t.state.name == "COMPLETE" for t in study.trials) == 1
    else:
        assert {p: (out / p).read_bytes() for p in before} == before


def test_a_training_that_cannot_save_says_the_checkpoint_it_keeps(tmp_path, run_cli, monkeypatch, trained_checkpoint):
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(trained_checkpoint, out / "ck.pt")
    before = (out / "ck.pt").read_bytes()
    disk_full_under(monkeypatch, out)
    code, _, err = run_cli("train", "paper", "--data", TINY_DATA, "--steps", "2", "--batch-size", "2", "--train-size",
                           "32x32", "--out", out / "ck.pt")
    line = says_one_line(err)
    assert code == 2 and f"{out / 'ck.pt'} keeps the last checkpoint saved, and the same command resumes from it" in line
    assert files(out) == ["ck.pt"] and (out / "ck.pt").read_bytes() == before


def test_a_data_cache_on_a_full_disk_is_one_line_and_nothing_of_it_is_kept(tmp_path, run_cli, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(cache))
    disk_full_under(monkeypatch, cache)
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:5:3")
    line = says_one_line(err)
    assert code == 2 and "cannot write the synthetic data cache (no space left on device)" in line, line
    assert "set ANYTIME_EXPLORER_CACHE to a folder on a disk with room; nothing of it was kept" in line
    assert files(cache) == []


def test_a_data_cache_that_cannot_fit_is_refused_before_a_frame_is_rendered(tmp_path, run_cli, monkeypatch):
    from explorer.data import synthetic
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9 - 2**20, 2**20))
    monkeypatch.setattr(synthetic, "_render_job", _no_work)
    code, _, err = run_cli("data", "inspect", "--data", "synthetic:500:100")
    line = says_one_line(err)
    assert code == 2 and "1.0 MiB free on its disk, and the synthetic data cache needs about" in line, line
    assert not (tmp_path / "cache").exists()


HDF5_ON_A_FILLING_DISK = """
import errno, os, sys
import numpy as np
from explorer import files
real_fdopen = os.fdopen

class Filling:   # a file on a disk with 200 kB left
    def __init__(self, raw):
        self.raw, self.written = raw, 0
    def write(self, data):
        self.written += len(data)
        if self.written > 200_000:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.raw.write(data)
    def __getattr__(self, name):
        return getattr(self.raw, name)
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        self.raw.close()

os.fdopen = lambda *args, **kwargs: Filling(real_fdopen(*args, **kwargs))
try:
    with files.writing_hdf5(sys.argv[1]) as out:
        rgb = out.file.create_dataset("rgb", (64, 64, 64, 3), np.uint8, chunks=(1, 64, 64, 3), compression="lzf")
        for i in range(64):
            rgb[i] = np.random.default_rng(i).integers(0, 255, (64, 64, 3), dtype=np.uint8)
except OSError as exc:
    print("refused", exc.errno == errno.ENOSPC, exc.filename)
"""


def test_hdf5_written_to_a_disk_that_fills_is_an_error_not_a_crash(tmp_path):
    """HDF5 (2.0) whose write failed crashes the process when the file is closed, even at exit (exit
    139): the writer's file never fails it, and the error comes after HDF5 closed the file."""
    target = tmp_path / "cache.h5"
    done = subprocess.run([sys.executable, "-c", HDF5_ON_A_FILLING_DISK, str(target)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    assert done.stdout.split() == ["refused", "True", str(target)]
    assert files(tmp_path) == []


@pytest.mark.slow
def test_a_data_cache_on_a_real_full_disk_is_one_line_not_a_segmentation_fault(tmp_path):
    """The case that crashed (exit 139): synthetic frames generated into a cache on a disk too small for
    them (9 MB, where they take 11 MB: the free-space check lets it start)."""
    (tmp_path / "disk").mkdir()
    done, left = on_full_disk(tmp_path / "disk", "9m", "data", "inspect", "--data", "synthetic:48:16",
                              env={"ANYTIME_EXPLORER_CACHE": str(tmp_path / "disk" / "cache")})
    line = says_one_line(done.stderr)
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert "cannot write the synthetic data cache (no space left on device)" in line
    assert left == ["cache"]     # the folder, empty


@pytest.mark.slow
def test_a_checkpoint_on_a_real_full_disk_is_one_line_and_leaves_no_scratch(tmp_path):
    """torch's checkpoint writer raises its own error over the disk's (``unexpected pos``): the line says
    the disk's."""
    (tmp_path / "disk").mkdir()
    done, left = on_full_disk(tmp_path / "disk", "1m", *writer("train", tmp_path / "disk"))
    line = says_one_line(done.stderr)
    assert done.returncode == 2 and "ck.pt: cannot write it (no space left on device)" in line, done.stderr
    assert left == []


def test_a_trial_stopped_by_a_full_disk_is_interrupted_not_failed_and_said_once(tmp_path, monkeypatch):
    """Not the candidate's fault: the resume tries it again (a failed trial is a result, never retried);
    Optuna's traceback of it is not shown (the search says it in one line), and a search worker stopped
    by it exits quietly, for its parent to say it."""
    import logging

    from explorer.study import search
    from explorer.study._stopping import _QuietCtrlC
    from explorer.study.retry import guarded, interrupted_trials
    full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "artifact"))

    def objective(trial):
        raise full

    study = optuna.create_study()
    study.optimize(guarded(objective, max_retries=2), n_trials=1, catch=(OSError,))
    assert list(interrupted_trials(study)) == [0]
    assert interrupted_trials(study)[0].startswith("interrupted (a write the machine refused): OSError")
    record = logging.LogRecord("optuna.study._optimize", logging.WARNING, __file__, 1, "Trial 0 failed with "
                               "parameters: {} because of ...", None, (OSError, full, None))
    assert _QuietCtrlC().filter(record) is False
    monkeypatch.setattr(search, "die_with_parent", lambda: None)
    monkeypatch.setattr(search, "_work", lambda *args: objective(None))
    with pytest.raises(SystemExit) as stopped:
        search.run_worker({}, None, None, None, 0, "reports", 1)
    assert stopped.value.code == 2


# -- a folder that cannot be written ---------------------------------------------------------------------

@pytest.mark.parametrize("command, says", [
    (["calibrate", "--quick", "--bundle", "/proc/x/b.tar"], "/proc/x: cannot write the bundle there"),
    (["calibrate", "--quick", "--out", "/proc/x/p.yaml"], "/proc/x: cannot write the profile there"),
])
def test_calibrate_onto_a_folder_that_cannot_be_written_is_one_line_before_any_measuring(run_cli, monkeypatch, command,
                                                                                         says):
    import explorer.calibration.bundle
    import explorer.calibration.calibrate
    monkeypatch.setattr(explorer.calibration.bundle, "write_bundle", _no_work)
    monkeypatch.setattr(explorer.calibration.calibrate, "calibrate", _no_work)
    code, _, err = run_cli(*command)
    assert code == 2 and says in says_one_line(err), err


def test_a_data_cache_that_cannot_be_written_is_one_line_before_any_training(run_cli, monkeypatch):
    import explorer.training.train
    from explorer.data import synthetic
    monkeypatch.setenv("ANYTIME_EXPLORER_CACHE", "/proc/x/cache")
    monkeypatch.setattr(synthetic, "_render_job", _no_work)
    monkeypatch.setattr(explorer.training.train, "train", _no_work)
    code, _, err = run_cli("train", "paper", "--data", "synthetic:7:3", "--steps", "1", "--out", "/tmp/never/ck.pt")
    line = says_one_line(err)
    assert code == 2 and "/proc/x/cache: cannot write the synthetic data cache there" in line, line
    assert "set ANYTIME_EXPLORER_CACHE to a folder you can write" in line and not Path("/tmp/never").exists()


def test_a_search_s_supernet_into_a_cache_that_cannot_be_written_is_refused_before_any_training(monkeypatch):
    from explorer.space import SearchSpace
    from explorer.supernet import train as supernet_train
    monkeypatch.setattr(supernet_train, "open_dataset", _no_work)
    with pytest.raises(UserError, match="/proc/x: cannot write the supernet there") as caught:
        supernet_train.train_supernet(SearchSpace.from_yaml("tiny"), TINY_DATA, out=Path("/proc/x/sn.pt"))
    assert "\n" not in str(caught.value)


READ_ONLY = {   # a command, given the read-only folder RO holding study 'cc'; what its line says
    "search resume": (lambda ro: fast_search(ro, "--trials", "2"), "cannot write the study's journal and lock there"),
    "report": (lambda ro: ["report", "--study", "cc", "--reports", ro], "cannot write the report there"),
    "train --out": (lambda ro: writer("train", ro / "o"), "cannot write the checkpoint there"),
    "supernet train --out": (lambda ro: writer("supernet train", ro / "o"), "cannot write the supernet there"),
    "the cache": (lambda ro: ["data", "inspect", "--data", "synthetic:5:3"], "cannot write the synthetic data cache"),
    "calibrate --bundle": (lambda ro: ["calibrate", "--quick", "--bundle", ro / "b.tar"], "cannot write the bundle"),
}


@pytest.mark.parametrize("case", list(READ_ONLY))
def test_a_read_only_folder_is_refused_in_one_line_and_left_as_it_was(tmp_path, case, searched_study):
    ro = tmp_path / "ro"
    shutil.copytree(searched_study, ro)
    before = {p: (ro / p).read_bytes() if (ro / p).is_file() else None for p in files(ro)}
    args, says = READ_ONLY[case]
    env = {"ANYTIME_EXPLORER_CACHE": str(ro / "cache")} if case == "the cache" else {}
    with read_only(ro) as prefix:
        done = explorer(*args(ro), env=env, prefix=prefix)
    line = says_one_line(done.stderr)
    assert done.returncode == 2 and says in line and str(ro) in line, done.stderr
    assert {p: (ro / p).read_bytes() if (ro / p).is_file() else None for p in files(ro)} == before


def _no_work(*args, **kwargs):
    raise AssertionError("the command went on to its work")


def test_an_export_into_a_folder_that_cannot_be_written_is_one_line_before_any_work(run_cli, monkeypatch):
    import explorer.study.export
    monkeypatch.setattr(explorer.study.export, "export_from_study", _no_work)
    code, _, err = run_cli("export", "--study", "cc", "--out", "/proc/x/model")
    line = says_one_line(err)
    assert code == 2 and "/proc/x: cannot write the export there" in line, line
    assert "give --out a folder you can write" in line
