"""``explorer search``'s progress bars: what the search tells its observer, shown as it goes."""

from __future__ import annotations

import time

from explorer.cli._common import smallest_status
from explorer.study.run import SearchObserver


class SearchProgress(SearchObserver):
    """The progress bars of one search: its trials, then one bar per phase as the phase starts."""

    def __init__(self, bar, study: str, trials: int | None, timeout: float | None) -> None:
        self.bar, self.timeout = bar, timeout
        self.task = bar.add_task(f"search {study}", total=trials, status="starting (data, baselines)")
        self.phases: dict = {}
        self.t0 = time.time()              # reset when sampling starts: the timeout counts from there
        self.said = {"plan": False, "changes": 0}

    def supernet(self, step: int, steps: int, record: dict) -> None:
        if "supernet" not in self.phases:
            self.phases["supernet"] = self.bar.add_task("supernet (once per space, data, recipe)", total=steps,
                                                        status="")
        self.bar.update(self.phases["supernet"], completed=step, status=f"largest {record['largest']:.3f}, "
                        f"{smallest_status(record)}")

    def finalist(self, i: int, n: int, what: str) -> None:
        if "finalists" not in self.phases:
            self.phases["finalists"] = self.bar.add_task("finalists (retraining)", total=n, status="")
        self.bar.update(self.phases["finalists"], completed=i, status=what)

    def envelope(self, i: int, n: int, what: str) -> None:
        if "envelope" not in self.phases:
            self.phases["envelope"] = self.bar.add_task("envelope (dedicated networks, in the time left)", total=n,
                                                        status="")
        self.bar.update(self.phases["envelope"], completed=i, status=what)

    def trial(self, study_obj, trial=None) -> None:
        import optuna
        from explorer.study.retry import counted_trials
        if "search_start" not in self.phases:
            self.phases["search_start"], self.t0 = True, time.time()
        complete = study_obj.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
        complete = [t for t in complete if t.values]
        best = min((t.values[0] for t in complete), default=float("nan"))
        last = f"trial {trial.number} {trial.state.name.lower()}" + (
            f" {trial.values[0]:.4f}" if trial is not None and trial.values else "") if trial else ""
        left = "" if self.timeout is None else f", {max(self.timeout - (time.time() - self.t0), 0) / 60:.1f} min left"
        self.bar.update(self.task, completed=counted_trials(study_obj), status=f"{last}  best {best:.4f}{left}")

    def poll(self, study_obj) -> None:
        """Worker processes sample: the bar follows the study as it stands."""
        self.trial(study_obj)

    def data(self, i: int, n: int) -> None:
        self.bar.update(self.task, status=f"generating synthetic scenes {i}/{n} (once, then cached)")

    def plan(self, plan) -> None:
        """Called again when a later phase re-plans: only what is new is said."""
        from explorer.console import err_console
        self.timeout = plan.sampling_s
        if not self.said["plan"]:
            err_console.print(plan.describe(), highlight=False)
        for change in plan.changes[self.said["changes"]:]:
            err_console.print(f"  plan: {change}", highlight=False)
        self.said.update(plan=True, changes=len(plan.changes))
