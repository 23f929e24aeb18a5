"""How one search runs, beside what it searches (its resolved :class:`~explorer.study.config.StudyContext`):
where the study is stored, how many workers sample and for how long (:class:`SearchRun`), and whom the
search tells what it does as it goes (:class:`SearchObserver`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from explorer.study.storage import REPORTS_DIR

if TYPE_CHECKING:
    import optuna

    from explorer.study.planning import Plan, TimeLimit


@dataclass(frozen=True)
class SearchRun:
    """One run of a search: its storage (default: the study's journal under ``reports``), the worker
    processes that sample, when sampling stops (``n_trials`` counted trials, or ``timeout_s`` seconds),
    and the whole run's ``time_limit``, which sizes the run to it first (then ``timeout_s`` is the most
    sampling may take)."""

    storage_url: str | None = None
    workers: int = 1
    n_trials: int | None = None
    timeout_s: float | None = 600.0
    time_limit: "TimeLimit | None" = None
    reports: Path = REPORTS_DIR


class SearchObserver:
    """What a search tells its caller as it goes; each method does nothing here, and a caller overrides
    those it shows (the command line's progress bars do all)."""

    def trial(self, study: "optuna.Study", trial: "optuna.trial.FrozenTrial") -> None:
        """A trial of this process ended."""

    def poll(self, study: "optuna.Study") -> None:
        """Every few seconds while worker processes sample."""

    def data(self, done: int, total: int) -> None:
        """Data being generated (once, then cached)."""

    def supernet(self, step: int, steps: int, record: dict) -> None:
        """A step of the supernet's training, with its losses."""

    def finalist(self, done: int, total: int, what: str) -> None:
        """The finalists' and baselines' retraining: what starts, what has no time left."""

    def plan(self, plan: "Plan") -> None:
        """The time plan, when it is made and each time a later phase changes it."""

    def envelope(self, done: int, total: int, what: str) -> None:
        """The envelope's dedicated networks, retrained in the time the finalists left."""
