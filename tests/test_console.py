"""Off a terminal (a log file, a pipe, nohup, CI) a long command is never silent: progress comes as lines,
one per phase and a heartbeat at least every EXPLORER_PROGRESS_EVERY seconds; a short one adds none."""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import TINY_DATA

ROOT = Path(__file__).resolve().parents[1]

WORK = """
import time
from explorer.console import Phases, progress
with progress(transient=True) as bar:
    quick = bar.add_task("quick", total=2, status="")
    bar.update(quick, completed=2)
with progress(transient=True) as bar:
    task = bar.add_task("search s", total=4, status="starting")
    for i in range(4):
        time.sleep(0.7)
        bar.update(task, completed=i + 1, status=f"trial {i}")
    phases = Phases(bar, "calibrating: ")
    phases("timing", 0, 2)
    time.sleep(2.5)                   # no update for a while: the heartbeat still speaks
    phases("timing", 2, 2)
print("finished")
"""


def _timed_lines(command: list[str], env: dict) -> tuple[int, list[tuple[float, str]]]:
    """Runs ``command`` with stdout and stderr on pipes; every line with when it arrived (seconds from
    the start)."""
    start = time.monotonic()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[tuple[float, str]] = []

    def read(stream):
        for line in stream:
            lines.append((time.monotonic() - start, line.rstrip("\n")))

    readers = [threading.Thread(target=read, args=(s,)) for s in (proc.stdout, proc.stderr)]
    for r in readers:
        r.start()
    code = proc.wait(timeout=900)
    for r in readers:
        r.join()
    return code, sorted(lines)


def test_off_a_terminal_progress_is_lines_per_phase_and_a_heartbeat():
    env = {**os.environ, "EXPLORER_PROGRESS_EVERY": "1"}
    code, lines = _timed_lines([sys.executable, "-c", WORK], env)
    assert code == 0
    text = [line for _, line in lines]
    assert not any(line.startswith("quick") for line in text)      # over within a second: no line
    assert any(line.startswith("search s: ") and "done" in line and "elapsed" in line and "left" in line
               for line in text), text
    assert any(line.startswith("search s: done (4/4)") for line in text), text
    assert any(line.startswith("calibrating: timing: started, 2 to do") for line in text), text
    assert any(line.startswith("calibrating: timing: 0/2 done") for line in text), text   # the heartbeat
    assert "\r" not in "".join(text) and text[-1] == "finished"
    times = [t for t, _ in lines]
    assert max(b - a for a, b in zip(times, times[1:])) < 2.5, lines


@pytest.mark.slow
def test_a_search_into_a_pipe_is_never_silent_for_long(tmp_path):
    every = 1
    env = {**os.environ, "EXPLORER_PROGRESS_EVERY": str(every)}
    code, lines = _timed_lines(
        [sys.executable, "-m", "explorer", "search", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32",
         "--input-size", "64x64", "--batch-size", "8", "--supernet-steps", "4", "--finalists", "1",
         "--finalist-steps", "4", "--tune-steps", "1", "--trials", "4", "--timeout", "0", "--study", "pipe",
         "--no-report", "--reports", str(tmp_path)], env)
    text = "\n".join(line for _, line in lines)
    assert code == 0, text
    assert "elapsed" in text and "finalists (retraining): done (4/4)" in text, text
    times = [0.0] + [t for t, _ in lines]
    gaps = [b - a for a, b in zip(times, times[1:])]
    # starting Python and torch takes a few seconds; from then on a line at least every few seconds
    assert gaps[0] < 30 and max(gaps[1:]) < every + 5, list(zip(gaps, text.splitlines()))
