"""Terminal output helpers: rich tables and progress bars, plain JSON when asked."""

from __future__ import annotations

import json
import os
import sys
from typing import Any

import pandas as pd
from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

#: off a terminal (a log, a pipe) rich would cut tables at 80 columns: lines this wide instead, unless
#: COLUMNS says otherwise
LOG_WIDTH = 200


def _console(stderr: bool) -> Console:
    stream = sys.stderr if stderr else sys.stdout
    wide = None if stream.isatty() or os.environ.get("COLUMNS") else LOG_WIDTH
    return Console(stderr=stderr, highlight=False, width=wide)


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


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.4e}"
    return str(v)


def print_frame(frame: pd.DataFrame, title: str | None = None) -> None:
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
