"""How a search stops: a Ctrl-C is one line saying what the study kept and how to resume (no Optuna
traceback, not even through its warning logger, however many times Ctrl-C is pressed); worker processes
stop with their parent, even when it is killed -9; ``--workers`` is bounded by what the machine holds."""

from __future__ import annotations

import logging
import os
import signal
import time
from contextlib import contextmanager
from typing import Iterator

import optuna

from explorer.errors import UserError, kept_if_refused, refused_write
from explorer.processes import interrupted_once, machine_workers
from explorer.study.storage import open_storage, redacted


class _QuietCtrlC(logging.Filter):
    """Drops Optuna's two warnings about a trial that Ctrl-C, or a write the machine refused (a full disk),
    stopped (its traceback, then "failed with value None"): the search says in one line what happened."""

    def __init__(self) -> None:
        super().__init__()
        self.trial: str | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        message = record.getMessage()
        if isinstance(exc, KeyboardInterrupt) or refused_write(exc) is not None:   # a full disk too
            self.trial = message.split(" failed", 1)[0]    # "Trial 12"
            return False
        return not (self.trial is not None and message.startswith(f"{self.trial} failed with value"))


@contextmanager
def quiet_ctrl_c() -> Iterator[None]:
    """While the block runs (``study.optimize``), a trial stopped by Ctrl-C is not logged by Optuna."""
    logger = logging.getLogger("optuna.study._optimize")
    quiet = _QuietCtrlC()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


@contextmanager
def ctrl_c_says_what_is_kept(url: str, study: str) -> Iterator[None]:
    """A Ctrl-C in the block ends it with ``KeyboardInterrupt("<what study kept, how to resume>")``;
    Ctrl-Cs after the first are ignored until then (the interrupted trial is recorded and retried). A
    write the disk refuses (full, read-only) says the same in its one line."""
    with interrupted_once(), kept_if_refused(lambda: study_kept(url, study)):
        try:
            yield
        except KeyboardInterrupt as exc:
            saved = getattr(exc, "saved", None)   # a training stopped at a step's end: what it saved, where
            inner = exc.kept if saved is not None and saved.exists() else None   # not a trial's scratch file
            line = study_kept(url, study)
            raise KeyboardInterrupt(f"{inner}; {line}" if inner else line) from exc


def study_kept(url: str, study: str) -> str:
    """What the study at ``url`` holds now, and how to resume it, in words."""
    where = url[len("journal:"):] if url.startswith("journal:") else redacted(url)
    try:
        trials = optuna.load_study(study_name=study, storage=open_storage(url, study, create=False)).get_trials(
            deepcopy=False)
    except (UserError, KeyError):
        return f"study '{study}' had no trial yet: run the same command again to start it"
    except Exception:   # storage unreadable now: say what is certain
        return f"study '{study}' keeps its finished trials in {where}: run the same command again to resume"
    done = sum(t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED) for t in trials)
    return (f"study '{study}' keeps its {done} finished trial(s) in {where}: run the same command again to resume "
            "(a trial cut short runs again)")


def check_workers(workers: int) -> None:
    """Refuses in one line more search workers than this machine can run at once."""
    if workers < 1:
        raise UserError("--workers must be at least 1")
    limit, why = machine_workers()
    if workers > limit:
        raise UserError(f"--workers {workers}: this machine runs at most {limit} search worker(s) at once ({why}): "
                        f"give --workers {limit} or fewer")


def end_workers(procs: list, interrupted: bool, grace_s: float = 30.0) -> None:
    """Waits for the worker processes ``procs`` to end. ``interrupted`` (Ctrl-C in the parent): each is
    sent SIGINT first, so that it records its trial as interrupted (to be tried again) and stops; those
    still running after ``grace_s`` (5 s when not interrupted) are terminated."""
    if interrupted:
        for p in procs:
            if p.is_alive() and p.pid:
                try:
                    os.kill(p.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
    deadline = time.time() + (grace_s if interrupted else 5.0)
    for p in procs:
        p.join(timeout=max(deadline - time.time(), 0.1))
    for p in procs:
        if p.is_alive():
            p.terminate()
            p.join(timeout=5)
