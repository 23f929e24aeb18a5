"""How a search stops (issue 89): Ctrl-C, once or twice, is one line saying what the study kept and how
to resume, exit 130, no traceback; kill -9 of a search leaves none of its workers running; --workers past
what the machine can run is one line, exit 2, with nothing written. Every wait polls for the state it
needs (a busy machine only makes it longer)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from explorer import processes
from explorer.study._stopping import _QuietCtrlC
from conftest import TINY_DATA, journal_trials

CLI_TINY = ["--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size", "64x64",
            "--proxy-steps", "400", "--batch-size", "8", "--no-report", "--timeout", "0", "--evaluator", "proxy",
            "--finalists", "0", "--no-baselines", "--trials", "50"]


def _search(tmp_path: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "explorer", "search", "--study", "s", "--reports", str(tmp_path),
                             *CLI_TINY, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, env={**os.environ, "EXPLORER_PROGRESS_EVERY": "100000"})


def _running(journal: Path) -> int:
    """How many trials are in training now (RUNNING, their candidate sampled)."""
    try:
        trials = journal_trials(journal, "s")
    except Exception:   # not written yet
        return 0
    return sum(t.state.name == "RUNNING" and "candidate_key" in t.user_attrs for t in trials)


def _wait_for(proc: subprocess.Popen, ready, what: str, limit_s: float = 600) -> None:
    deadline = time.time() + limit_s
    while not ready():
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"{what} never happened: {proc.communicate()}")
        time.sleep(0.1)


def _children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                found.append(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for a parent that does not reap it counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _left_after(pids: list[int], limit_s: float = 120) -> list[int]:
    """Those of ``pids`` still running once they all ended or ``limit_s`` passed (then killed)."""
    deadline = time.time() + limit_s
    while [pid for pid in pids if _alive(pid)] and time.time() < deadline:
        time.sleep(0.1)
    left = [pid for pid in pids if _alive(pid)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    return left


def _says_one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "[W " not in err
    return lines[0]


@pytest.mark.slow
@pytest.mark.parametrize("presses", [1, 2])
def test_ctrl_c_of_a_search_is_one_line_and_keeps_the_study(tmp_path, presses):
    journal = tmp_path / "s" / "journal.log"
    proc = _search(tmp_path)
    _wait_for(proc, lambda: _running(journal) >= 1, "a trial in training")
    for _ in range(presses):     # a terminal's Ctrl-C goes to the whole process group
        os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    line = _says_one_line(err)
    assert line.startswith("explorer: interrupted; study 's' keeps its ") and str(journal) in line
    assert "run the same command again to resume" in line
    trials = journal_trials(journal, "s")
    stopped = [t for t in trials if t.system_attrs.get("fail_reason") == "interrupted (Ctrl-C)"]
    assert len(stopped) == 1 and stopped[0].state.name == "FAIL"
    assert [t.user_attrs.get("retry_of") for t in trials].count(stopped[0].number) == 1   # tried again on resume
    assert not list((tmp_path / "s").glob(".*search-lock"))


@pytest.mark.slow
def test_ctrl_c_of_a_search_with_workers_stops_them_and_records_their_trials(tmp_path):
    journal = tmp_path / "s" / "journal.log"
    proc = _search(tmp_path, "--workers", "2")
    _wait_for(proc, lambda: _running(journal) >= 2, "two trials in training")
    workers = _children(proc.pid)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert _says_one_line(err).startswith("explorer: interrupted; study 's' keeps its ")
    assert not _left_after(workers)
    trials = journal_trials(journal, "s")
    assert "RUNNING" not in [t.state.name for t in trials]      # each worker recorded its trial
    assert sum(t.system_attrs.get("fail_reason") == "interrupted (Ctrl-C)" for t in trials) == 2


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_a_search_leaves_no_worker_running(tmp_path):
    journal = tmp_path / "s" / "journal.log"
    proc = _search(tmp_path, "--workers", "2")
    _wait_for(proc, lambda: _running(journal) >= 2, "two trials in training")
    workers = _children(proc.pid)
    assert len(workers) >= 2, workers
    os.kill(proc.pid, signal.SIGKILL)       # the parent alone, as the OOM killer would
    proc.communicate(timeout=60)
    assert not _left_after(workers), "workers outlived their parent"


def test_more_workers_than_the_machine_runs_is_one_line_and_writes_nothing(tmp_path, run_cli, monkeypatch):
    monkeypatch.setattr(processes, "_cores", lambda: 2)
    code, _, err = run_cli("search", "--study", "w", "--reports", tmp_path, "--workers", "3", *CLI_TINY)
    assert code == 2 and len(err.splitlines()) == 1
    assert "--workers 3: this machine runs at most 2 search worker(s) at once (2 core(s)" in err
    assert not (tmp_path / "w").exists()


def test_workers_are_bounded_by_free_memory(monkeypatch):
    monkeypatch.setattr(processes, "_cores", lambda: 64)
    monkeypatch.setattr(processes, "_free_memory", lambda: 5 * processes.WORKER_BYTES + 1)
    limit, why = processes.machine_workers()
    assert limit == 5 and "64 core(s)" in why and "GB of memory free" in why
    monkeypatch.setattr(processes, "_free_memory", lambda: 0)
    assert processes.machine_workers()[0] == 1
    monkeypatch.setattr(processes, "_free_memory", lambda: None)   # cannot say: the cores bound it
    assert processes.machine_workers()[0] == 64


def test_optuna_says_nothing_of_a_trial_stopped_by_ctrl_c():
    import logging
    quiet = _QuietCtrlC()

    def record(message: str, exc: BaseException | None = None) -> logging.LogRecord:
        info = (type(exc), exc, None) if exc else None
        return logging.LogRecord("optuna.study._optimize", logging.WARNING, __file__, 1, message, None, info)

    assert quiet.filter(record("Trial 3 failed with parameters: {} because of ...", KeyboardInterrupt())) is False
    assert quiet.filter(record("Trial 3 failed with value None.")) is False
    assert quiet.filter(record("Trial 4 failed with parameters: {} because of ...", ValueError("x")))   # a fault
    assert quiet.filter(record("Trial 4 failed with value None."))
