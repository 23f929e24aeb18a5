"""Scratch folders that a killed process does not leave behind, and SIGTERM that unwinds.

Every scratch folder of the package (exported graphs, optimised sessions, a calibration bundle: up to
hundreds of MB) is made by :func:`scratch_dir`, in the system's temporary folder, named
``explorer-PID-WHAT-XXXXXXXX``. Ctrl-C, and SIGTERM inside :func:`sigterm_unwinds`, unwind the ``with``
blocks that remove them; SIGKILL cannot be caught, so each new scratch folder first removes those of
processes no longer alive. Here, in the probe, because the probe ships alone (``probe.pyz``) and every
other layer may import it; ``explorer.files`` offers the same names.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

PREFIX = "explorer-"
_OWNED = re.compile(rf"{re.escape(PREFIX)}(\d+)-.+")


def process_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # someone else's live process
        return True
    return True


def remove_stale_scratch(root: "str | Path | None" = None) -> list[Path]:
    """Removes the scratch folders (``explorer-PID-...``) in ``root`` (default: the system's temporary
    folder) whose process is no longer alive; returns what it removed."""
    root = Path(root if root is not None else tempfile.gettempdir())
    removed = []
    try:
        entries = [e for e in os.scandir(root) if e.name.startswith(PREFIX)]
    except OSError:
        return removed
    for entry in entries:
        m = _OWNED.fullmatch(entry.name)
        if not m or int(m.group(1)) == os.getpid() or process_alive(int(m.group(1))):
            continue
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)   # another user's stays: /tmp is sticky
            if not os.path.exists(entry.path):
                removed.append(Path(entry.path))
    return removed


def scratch_dir(what: str = "scratch") -> tempfile.TemporaryDirectory:
    """``tempfile.TemporaryDirectory`` named ``explorer-PID-WHAT-...``, made after removing the scratch
    folders of dead processes (``remove_stale_scratch``). Use it as ``with scratch_dir("export") as tmp``."""
    remove_stale_scratch()
    return tempfile.TemporaryDirectory(prefix=f"{PREFIX}{os.getpid()}-{what}-")


def remove_own_scratch(root: "str | Path | None" = None) -> None:
    """Removes this process's scratch folders in ``root`` (default: the system's temporary folder): for a
    process that SIGTERM is ending, whose signal may have come between making a folder and the ``with``
    block that removes it, or in the middle of removing it."""
    root = Path(root if root is not None else tempfile.gettempdir())
    try:
        entries = [e for e in os.scandir(root) if e.name.startswith(f"{PREFIX}{os.getpid()}-")]
    except OSError:
        return
    for entry in entries:
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)


@contextmanager
def sigterm_unwinds() -> Iterator[None]:
    """While the block runs, SIGTERM raises ``SystemExit(143)`` in the main thread, so that ``with`` and
    ``finally`` blocks (scratch folders, half-written files) unwind as on Ctrl-C; by default Python
    ends at once and leaves them. A second SIGTERM ends the process at once. Off the main thread, or
    where SIGTERM is ignored, nothing changes."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) == signal.SIG_IGN:
        yield
        return

    def unwind(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a cleanup that hangs can still be ended
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, unwind)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
