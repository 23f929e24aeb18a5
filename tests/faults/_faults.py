"""What the fault suite shares: a search small enough to run in seconds, the one line a refusal is, a
disk that fills under a folder, a folder that cannot be written, a process that no longer runs, and
waiting for a search in a child process to reach a state.

A full disk is simulated in the process itself: flushing a file under the folder to disk (``os.fsync``,
which every atomic writer and the study journal call before they rename or go on) fails with ENOSPC, as
it does on a disk that filled while the file was written. Where this machine lets a test mount file
systems of its own (root, ``unshare``), a command also runs on a real full disk (a small tmpfs) and
on a real read-only folder (a read-only bind mount), each in a mount namespace of its own that ends
with the command: nothing is left mounted."""

from __future__ import annotations

import errno
import os
import shutil
import stat
import subprocess
import sys
import time
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Iterator

import pytest

from conftest import TINY_DATA, journal_trials

#: a search over the tiny space that stops after its trials (proxy, 2 steps, no finalists, no report)
FAST_SEARCH = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size", "32x32",
               "--evaluator", "proxy", "--proxy-steps", "2", "--batch-size", "8", "--no-baselines", "--finalists",
               "0", "--timeout", "0", "--no-report"]


def fast_search(tmp_path, *extra) -> list:
    """``explorer search`` of study 'cc' in ``tmp_path``, one trial, in seconds (``extra`` after it)."""
    return ["search", "--study", "cc", *FAST_SEARCH, "--trials", "1", "--reports", tmp_path, *extra]


#: a search that keeps training (400 proxy steps, 50 trials) until a test stops it
CLI_TINY = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size", "64x64",
            "--proxy-steps", "400", "--batch-size", "8", "--no-report", "--timeout", "0", "--evaluator", "proxy",
            "--finalists", "0", "--no-baselines", "--trials", "50"]


def search_process(tmp_path: Path, *extra: str) -> subprocess.Popen:
    """``explorer search`` of study 's' (``CLI_TINY``) in a child process, in a session of its own."""
    return subprocess.Popen([sys.executable, "-m", "explorer", "search", "--study", "s", "--reports", str(tmp_path),
                             *CLI_TINY, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, "EXPLORER_PROGRESS_EVERY": "100000"})


def running(journal: Path) -> int:
    """How many trials are in training now (RUNNING, their candidate sampled)."""
    try:
        trials = journal_trials(journal, "s")
    except Exception:   # not written yet
        return 0
    return sum(t.state.name == "RUNNING" and "candidate_key" in t.user_attrs for t in trials)


def wait_for(proc: subprocess.Popen, ready, what: str, limit_s: float = 600) -> None:
    deadline = time.time() + limit_s
    while not ready():
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"{what} never happened: {proc.communicate()}")
        time.sleep(0.1)


def says_one_line(err: str) -> str:
    """The one line on stderr (no traceback, no warning before it)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "[W " not in err
    return lines[0]


def files(root: Path) -> list[str]:
    """Every file and folder under ``root``, relative to it, sorted."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def scratch(root: Path) -> list[str]:
    """What a writer would leave under ``root``: scratch files and folders (``*.tmp*``), ``*.part``, and
    the search's lock."""
    return [p for p in files(root) if ".tmp" in Path(p).name or Path(p).name.endswith((".part", "search-lock"))]


def sqlite_url(tmp_path) -> str:
    return f"sqlite:///{tmp_path / 's' / 'study.db'}"


def dead_pid() -> int:
    """The id of a process that has ended."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def disk_full_under(monkeypatch, folder: Path) -> None:
    """From now on (in this process) the disk under ``folder`` is full: a file there flushed to disk
    (``os.fsync``) fails with ENOSPC, as on a disk that filled while the file was written."""
    if not sys.platform.startswith("linux"):
        pytest.skip("finds a descriptor's file through /proc/self/fd")
    real = os.fsync
    root = str(Path(folder).resolve())

    def fsync(fd: int) -> None:
        try:
            path = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            path = ""
        if path == root or path.startswith(root + os.sep):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)


@lru_cache(maxsize=None)
def _can_mount() -> bool:
    """Whether this process may mount file systems in a mount namespace of its own (root, unshare)."""
    if os.geteuid() != 0 or not shutil.which("unshare") or not sys.platform.startswith("linux"):
        return False
    probe = Path(os.environ.get("TMPDIR", "/tmp")) / f"explorer-mount-probe-{os.getpid()}"
    probe.mkdir(exist_ok=True)
    try:
        return subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c",
                               'mount -t tmpfs -o size=64k tmpfs "$0"', str(probe)], capture_output=True).returncode == 0
    finally:
        probe.rmdir()


def explorer(*args, env: dict | None = None, prefix: list[str] | None = None) -> subprocess.CompletedProcess:
    """``explorer ARGS`` in a child process (after ``prefix``, e.g. a mount namespace's), its output as text."""
    return subprocess.run([*(prefix or []), sys.executable, "-m", "explorer", *map(str, args)], capture_output=True,
                          text=True, env={**os.environ, **(env or {})}, timeout=600)


def on_full_disk(mount: Path, size: str, *args, env: dict | None = None) -> tuple[subprocess.CompletedProcess, list]:
    """``explorer ARGS`` with a tmpfs of ``size`` (e.g. 1m) mounted on ``mount`` (an empty folder), the
    command's result and what it left on that disk (every path under ``mount``, listed before the
    namespace ends and takes the tmpfs with it). Skipped where this machine cannot mount one."""
    if not _can_mount():
        pytest.skip("mounting a small tmpfs needs root and unshare (a disk that fills is simulated elsewhere)")
    script = ('mount -t tmpfs -o size="$1" tmpfs "$0" || exit 99; shift; "$@"; rc=$?; '
              'echo "--- left on the disk:" >&2; cd "$0" && find . -mindepth 1 >&2; exit $rc')
    done = explorer(*args, env=env, prefix=["unshare", "-m", "--propagation", "private", "sh", "-c", script,
                                            str(mount), size])
    assert done.returncode != 99, done.stderr
    err, _, listing = done.stderr.partition("--- left on the disk:\n")
    done.stderr = err
    return done, sorted(line[2:] for line in listing.splitlines() if line.startswith("./"))


@contextmanager
def read_only(folder: Path) -> Iterator[list[str]]:
    """``folder`` read-only for the commands run in the block with the prefix it yields (put before
    ``python -m explorer``): a read-only bind mount in a mount namespace of their own where this process
    is root (permission bits do not stop root), else the write bits taken from it and every folder under
    it (given back after). Skipped where neither holds."""
    if os.geteuid() == 0:
        if not _can_mount():
            pytest.skip("a folder root cannot write needs a read-only mount (unshare)")
        yield ["unshare", "-m", "--propagation", "private", "sh", "-c",
               'mount --bind -o ro "$0" "$0" || exit 99; exec "$@"', str(folder)]
        return
    folders = [folder, *[p for p in folder.rglob("*") if p.is_dir()]]
    modes = {p: p.stat().st_mode for p in folders}
    for p in folders:
        p.chmod(modes[p] & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    try:
        yield []
    finally:
        for p, mode in modes.items():
            p.chmod(mode)


#: what the fixtures below made, once per process (each module importing them holds a fixture of its own).
#: A module uses them by importing ``searched_study_fixture`` and ``trained_checkpoint_fixture``.
_MADE: dict[str, Path] = {}


@pytest.fixture(scope="session", name="searched_study")
def searched_study_fixture(tmp_path_factory) -> Path:
    """A reports folder holding study 'cc' with one finished trial (:func:`fast_search`), made once: copy
    it (``shutil.copytree``) before a command writes to it."""
    if "study" not in _MADE:
        from explorer.cli import main
        root = tmp_path_factory.mktemp("study")
        assert main([str(a) for a in fast_search(root)]) == 0
        _MADE["study"] = root
    return _MADE["study"]


@pytest.fixture(scope="session", name="trained_checkpoint")
def trained_checkpoint_fixture(tmp_path_factory) -> Path:
    """A checkpoint of the paper design trained one step at 32x32, made once (read it, do not write it)."""
    if "checkpoint" not in _MADE:
        from explorer.cli import main
        out = tmp_path_factory.mktemp("checkpoint") / "ck.pt"
        assert main(["train", "paper", "--data", TINY_DATA, "--steps", "1", "--batch-size", "2", "--train-size",
                     "32x32", "--out", str(out)]) == 0
        _MADE["checkpoint"] = out
    return _MADE["checkpoint"]


#: a command that writes into the folder OUT, for every kind of output (CK: a checkpoint, STUDY: reports
#: holding study 'cc'); what it writes there
WRITERS = {
    "train": (["train", "paper", "--data", TINY_DATA, "--steps", "1", "--batch-size", "2", "--train-size", "32x32",
               "--out", "OUT/ck.pt"], "ck.pt"),
    "supernet train": (["supernet", "train", "--space", "tiny", "--data", TINY_DATA, "--steps", "1", "--batch-size",
                        "2", "--train-size", "32x32", "--out", "OUT/sn.pt"], "sn.pt"),
    "export": (["export", "--checkpoint", "CK", "--input-size", "64x64", "--out", "OUT/model"], "model"),
    "report": (["report", "--study", "cc", "--reports", "STUDY", "--out", "OUT"], "report.html"),
    "search": ([*fast_search("OUT", "--trials", "2")], "cc"),
}


def writer(name: str, out: Path, checkpoint: Path | None = None, study: Path | None = None) -> list[str]:
    """The arguments of ``WRITERS[name]`` writing into ``out``."""
    args, _ = WRITERS[name]
    swap = {"OUT": str(out), "CK": str(checkpoint), "STUDY": str(study)}
    return [swap.get(a, a) if a in swap else a.replace("OUT/", f"{out}/") for a in map(str, args)]
