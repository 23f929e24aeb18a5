"""Terminal output helpers: rich tables and progress bars, plain JSON when asked."""

from __future__ import annotations

import json
import os
import sys
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


def progress(transient: bool = False) -> Progress:
    """A progress bar on stderr (so --json output stays clean)."""
    return _Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                     TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[status]}"),
                     console=err_console, transient=transient)


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
