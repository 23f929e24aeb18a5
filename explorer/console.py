"""Terminal output helpers: rich tables and progress bars, plain JSON when asked."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

if TYPE_CHECKING:   # pandas is imported by the commands that print tables: the runtime install has none
    import pandas as pd

#: off a terminal (a log, a pipe) rich would cut tables at 80 columns: lines this wide instead, unless
#: COLUMNS says otherwise
LOG_WIDTH = 200


def _console(stderr: bool) -> Console:
    stream = sys.stderr if stderr else sys.stdout
    wide = None if stream.isatty() or os.environ.get("COLUMNS") else LOG_WIDTH
    # soft_wrap: a printed line is never cut by rich (the terminal wraps it), so a path or a command in
    # it can be copied whole; tables still fit the width
    return Console(stderr=stderr, highlight=False, width=wide, soft_wrap=True)


console = _console(stderr=False)
err_console = _console(stderr=True)


class _Progress(Progress):
    """A progress bar that disappears when the work it shows fails: the error is then the one line the
    user reads on stderr, with no bar's remnant above it."""

    def __exit__(self, exc_type, exc_val, exc_tb) -> None:
        if exc_type is None:
            return super().__exit__(exc_type, exc_val, exc_tb)
        # Progress.stop() would draw the bar once more and, off a terminal, add a blank line
        self.live.transient = True
        self.live.stop()


#: off a terminal, how often (seconds) a long command says how far it is; EXPLORER_PROGRESS_EVERY sets it
PROGRESS_EVERY_S = 30.0


class _LogProgress(_Progress):
    """Progress off a terminal (a log file, a pipe, ``nohup``, CI), where a bar redrawn in place shows
    nothing: plain lines on stderr instead. Nothing for work that ends within ``every`` seconds (a short
    command's error stays the one line on stderr); after that, a line for each unfinished task, then a
    line as each phase (a task) starts or ends, and a heartbeat line whenever ``every`` seconds pass
    without one: what, done/total, elapsed, about how long is left, its status."""

    def __init__(self, *columns, every: float, **kwargs) -> None:
        super().__init__(*columns, disable=True, **kwargs)
        self.every, self._talking = every, False
        self._last = time.monotonic()
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, name="progress-lines", daemon=True)

    def __enter__(self) -> "_LogProgress":
        self._last = time.monotonic()
        self._beat.start()
        return super().__enter__()

    def __exit__(self, exc_type, exc_val, exc_tb) -> None:
        self._stop.set()
        self._beat.join()
        return super().__exit__(exc_type, exc_val, exc_tb)

    def add_task(self, description: str, *args, **kwargs) -> TaskID:
        task_id = super().add_task(description, *args, **kwargs)
        if self._talking and kwargs.get("visible", True):
            self._say(self._tasks[task_id], "started")
        return task_id

    def update(self, task_id: TaskID, **kwargs) -> None:
        with self._lock:
            task = self._tasks[task_id]
            before = (task.visible, task.description, task.finished)
        super().update(task_id, **kwargs)
        if not self._talking or not task.visible:
            return
        if (task.visible, task.description) != before[:2]:
            self._say(task, "started")
        elif task.finished and not before[2]:
            self._say(task, "done")

    def _heartbeat(self) -> None:
        while not self._stop.wait(min(1.0, self.every)):
            if time.monotonic() - self._last >= self.every:
                self._talking = True
                with self._lock:
                    busy = [t for t in self._tasks.values() if t.visible and not t.finished]
                for task in busy:
                    self._say(task)
                self._last = time.monotonic()

    def _say(self, task, event: str | None = None) -> None:
        """``task``'s line: ``event`` (started, done) or, for a heartbeat, how much is done; the time it
        has run and, from its average pace, about how long it has left."""
        done = f"{task.completed:g}" + (f"/{task.total:g}" if task.total else "")
        elapsed = task.elapsed or 0.0
        parts = [f"{event} ({done})" if event == "done" else event or f"{done} done", f"{_clock(elapsed)} elapsed"]
        if event == "started":
            parts = ["started" + (f", {task.total:g} to do" if task.total else "")]
        if event is None and task.total and 0 < task.completed < task.total:
            parts.append(f"about {_clock(elapsed / task.completed * (task.total - task.completed))} left")
        status = str(task.fields.get("status") or "")
        line = f"{task.description}: {', '.join(parts)}" + (f"; {status}" if status else "")
        self.console.print(line, markup=False, highlight=False, soft_wrap=True)
        self._last = time.monotonic()


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    return f"{minutes // 60}:{minutes % 60:02d}:{secs:02d}" if minutes >= 60 else f"{minutes}:{secs:02d}"


def progress(transient: bool = False) -> Progress:
    """A progress bar on stderr (so --json output stays clean); off a terminal, lines every so often
    instead (:class:`_LogProgress`)."""
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[status]}"))
    if not err_console.is_terminal:
        every = float(os.environ.get("EXPLORER_PROGRESS_EVERY", PROGRESS_EVERY_S))
        return _LogProgress(*columns, every=every, console=err_console, transient=transient)
    return _Progress(*columns, console=err_console, transient=transient)


class Phases:
    """``progress(what, done, total)`` of work in phases (``explorer calibrate``'s: exporting, timing,
    timing again, ...) on ``bar``, one task per phase, each counted from 0: rich stops a task's clock for
    good once its count reaches its total, so one task carried on from phase to phase showed a frozen
    clock and an ETA of 0:00:00 while the work went on. A phase that starts again (a second pass of
    timing again) takes the place of its earlier line. ``prefix`` goes before every phase's name."""

    def __init__(self, bar: Progress, prefix: str = "") -> None:
        self.bar, self.prefix = bar, prefix
        self.task: TaskID | None = None
        self.what, self.done = "", 0

    def __call__(self, what: str, done: int, total: int | None) -> None:
        if self.task is None or what != self.what or done < self.done:
            for earlier in [t.id for t in self.bar.tasks if t.description == self.prefix + what]:
                self.bar.remove_task(earlier)
            self.task, self.what = self.bar.add_task(self.prefix + what, total=total, status=""), what
        self.done = done
        self.bar.update(self.task, completed=done, total=total)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.4e}"
    return str(v)


def print_frame(frame: pd.DataFrame, title: str | None = None) -> None:
    import pandas as pd
    table = Table(title=title, show_lines=False)
    for col in frame.columns:   # a cell that does not fit wraps, never ends in an ellipsis
        table.add_column(str(col), justify="right" if pd.api.types.is_numeric_dtype(frame[col]) else "left",
                         overflow="fold")
    for row in frame.itertuples(index=False):
        table.add_row(*(_fmt(v) for v in row))
    console.print(table)


def print_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    if isinstance(o, tuple):
        return list(o)
    return str(o)
