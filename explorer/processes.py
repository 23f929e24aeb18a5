"""Processes that stop cleanly: Ctrl-C ends training at a step's end with its weights saved, a second
Ctrl-C does not tear what the first one is saving, and worker processes die with their parent.

- :class:`StopAtStep`: a training loop's Ctrl-C (SIGINT) or SIGTERM (under ``sigterm_unwinds``) is
  held until the step running ends; then the weights reached are saved (atomically, by the loop's own
  save) and the loop ends with ``KeyboardInterrupt("<what was kept>")``. A second signal before the
  step ends stops at once, saying that nothing more was saved.
- :func:`interrupted_once`: a search's first Ctrl-C raises ``KeyboardInterrupt``; the ones after it are
  ignored while the search records its interrupted trial and lets its lock go.
- :func:`die_with_parent`: a worker process is killed when its parent dies (even by kill -9).
- :func:`machine_workers`: how many worker processes this machine holds (cores, free memory).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator


class _Once:
    """A SIGINT handler: the first signal raises ``KeyboardInterrupt``, the next ones are ignored. While
    it ``defer``s (a search's trials), the first is only noted: it is raised at the next safe point."""

    def __init__(self) -> None:
        self.fired = self.defer = False

    def __call__(self, signum, frame) -> None:
        if not self.fired:
            self.fired = True
            if not self.defer:
                raise KeyboardInterrupt


@contextmanager
def held_between_trials() -> Iterator[Callable[[], bool]]:
    """Under :func:`interrupted_once`, a Ctrl-C in the block is raised only at safe points: at the end of a
    training step (:class:`StopAtStep`), or where the block asks (it gets a function saying whether a
    Ctrl-C came: a search stops between trials), or when the block ends; never inside a storage write
    (Optuna's journal lock is not safe to interrupt). Elsewhere it changes nothing."""
    held = signal.getsignal(signal.SIGINT) if _main_thread() else None
    if not isinstance(held, _Once) or held.fired:
        yield lambda: False
        return
    held.defer = True
    try:
        yield lambda: held.fired
    finally:
        held.defer = False
    if held.fired:
        raise KeyboardInterrupt


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def interrupted_once() -> Iterator[None]:
    """While the block runs, the first Ctrl-C raises ``KeyboardInterrupt`` and later ones are ignored
    (a double Ctrl-C cannot cut the bookkeeping of the first one short). Where SIGINT is not Python's
    own handler (ignored, or someone else's), or off the main thread, nothing changes."""
    if not _main_thread() or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    previous = signal.signal(signal.SIGINT, _Once())
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class StopAtStep:
    """Holds Ctrl-C (and SIGTERM where ``sigterm_unwinds`` turns it into ``SystemExit``) until the
    training step running ends: call :meth:`check` with the step reached after each one. ``save(step)``
    writes the checkpoint (atomically) to ``path``; None when the loop has no checkpoint file. Not
    ``active``: signals act as they would without it."""

    def __init__(self, save: Callable[[int], None] | None, path: str | Path | None, start: int, total: int,
                 what: str = "weights", active: bool = True) -> None:
        self.save, self.path, self.start, self.total, self.what = save, path, start, total, what
        self.active = active
        self.pending: int | None = None
        self.previous: dict[int, object] = {}

    def __enter__(self) -> "StopAtStep":
        if not self.active or not _main_thread():
            return self
        held = signal.getsignal(signal.SIGINT)
        if held is signal.default_int_handler or (isinstance(held, _Once) and (held.defer or not held.fired)):
            self.previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._signal)
            if isinstance(held, _Once) and held.fired:   # a Ctrl-C held since before: stop after the first step
                self.pending = signal.SIGINT
        term = signal.getsignal(signal.SIGTERM)
        if callable(term):    # sigterm_unwinds': by default SIGTERM ends the process at once
            self.previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._signal)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    def _restore(self) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        self.previous = {}

    def _signal(self, signum, frame) -> None:
        if self.pending is None:
            self.pending = signum
            return
        previous = self.previous.get(signum)
        if isinstance(previous, _Once):    # a search's: its later Ctrl-Cs are ignored
            return
        self._restore()
        kept = f" ({self.path} keeps the last checkpoint saved)" if self.path and Path(self.path).is_file() else ""
        if signum == signal.SIGINT:
            raise KeyboardInterrupt(f"interrupted again before the step ended: nothing more was saved{kept}")
        _raise_previous(previous, signum)

    def check(self, step: int) -> None:
        """Ends the loop here, with what was reached saved, when a signal came during the step: raises
        ``KeyboardInterrupt`` saying what was kept (``kept``: what was saved, or None; ``saved``: the file), or
        for SIGTERM ``SystemExit`` as the handler it held would have."""
        if self.pending is None:
            return
        signum, previous = self.pending, self.previous.get(self.pending)
        self._restore()
        kept = self._keep(step)
        if signum != signal.SIGINT:
            _raise_previous(previous, signum)
        if isinstance(previous, _Once):
            previous.fired = True
        nothing = "nothing was saved" + (" (no checkpoint file was given)" if self.save is None else "")
        interrupt = KeyboardInterrupt(f"{kept}: run the same command again to resume from there" if kept else nothing)
        interrupt.kept, interrupt.saved = kept, Path(self.path) if kept else None
        raise interrupt

    def _keep(self, step: int) -> str | None:
        """Saves the state at ``step`` where there is something new to save; what was saved, in words."""
        if self.save is None or step <= self.start:
            return None
        self.save(step)
        return f"the {self.what} at step {step} of {self.total} are saved in {self.path}"


def _raise_previous(previous: object, signum: int) -> None:
    """Lets ``previous`` (``sigterm_unwinds``' handler: ``SystemExit``) handle ``signum``."""
    if callable(previous):
        previous(signum, None)
    raise SystemExit(128 + signum)


PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Makes this process (a spawned worker) die when its parent does, however the parent ends (kill -9
    included): on Linux the kernel sends SIGKILL (``prctl(PR_SET_PDEATHSIG)``); elsewhere a thread
    watches the parent's pid. A parent already gone ends this process at once."""
    import multiprocessing
    parent = multiprocessing.parent_process()
    ppid = parent.pid if parent is not None and parent.pid else os.getppid()
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
                if os.getppid() != ppid:   # the parent died before the prctl
                    os._exit(1)
                return
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        import time
        while os.getppid() == ppid:
            time.sleep(1.0)
        os._exit(1)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


#: what one search worker holds: torch, the data, a network in training (measured: about 0.5 GB on
#: the tiny space, up to 1 GB with the default space's data)
WORKER_BYTES = 1 << 30


def _free_memory() -> int | None:
    """Bytes of memory this machine can still give (MemAvailable), or None where it cannot say."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def machine_workers(per_worker: int = WORKER_BYTES) -> tuple[int, str]:
    """(the most worker processes this machine can run at once, why): one per core this process may
    use, and no more than its free memory holds at ``per_worker`` bytes each."""
    cores = _cores()
    free = _free_memory()
    by_memory = cores if free is None else max(free // per_worker, 1)
    why = f"{cores} core(s)"
    if free is not None:
        why += f", {free / 2**30:.1f} GB of memory free at about {per_worker / 2**30:.1f} GB a worker"
    return max(min(cores, by_memory), 1), why
