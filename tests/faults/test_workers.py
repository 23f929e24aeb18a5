"""Faults of a search's worker processes (issue 89): Ctrl-C of a search with workers stops them, each
recording its trial; kill -9 of a search leaves none of its workers running; --workers past what the
machine can run (cores, free memory) is one line, exit 2, with nothing written. Every wait polls for
the state it needs (a busy machine only makes it longer)."""

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from explorer import processes
from conftest import journal_trials
from _faults import CLI_TINY, running, says_one_line, search_process, wait_for

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


@pytest.mark.slow
def test_ctrl_c_of_a_search_with_workers_stops_them_and_records_their_trials(tmp_path):
    journal = tmp_path / "s" / "journal.log"
    proc = search_process(tmp_path, "--workers", "2")
    wait_for(proc, lambda: running(journal) >= 2, "two trials in training")
    workers = _children(proc.pid)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert says_one_line(err).startswith("explorer: interrupted; study 's' keeps its ")
    assert not _left_after(workers)
    trials = journal_trials(journal, "s")
    assert "RUNNING" not in [t.state.name for t in trials]      # each worker recorded its trial
    assert sum(t.system_attrs.get("fail_reason") == "interrupted (Ctrl-C)" for t in trials) == 2


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_a_search_leaves_no_worker_running(tmp_path):
    journal = tmp_path / "s" / "journal.log"
    proc = search_process(tmp_path, "--workers", "2")
    wait_for(proc, lambda: running(journal) >= 2, "two trials in training")
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
