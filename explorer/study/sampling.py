"""The search's sampler: Optuna's TPE, reading a bounded view of the study.

TPE splits the finished trials into the best few (at most 25, its ``gamma``) and the rest, and models
each; Optuna re-reads and re-decomposes every finished trial at every ask, so an ask costs time in
proportion to the trials so far (about 20 ms at 600 trials on a laptop core, 100 ms at 3,000). A
search that estimates thousands of candidates (a GPU does 1,000 a minute) would spend most of its
time there. :class:`RecentTrialsTPE` hands TPE a view of the study instead: the best trials (TPE's
"good" group, the same as over the whole study) and the most recent ones (its "bad" group, where
TPE's own weights already fade the older trials), at most ``2 * window`` trials, so an ask costs the
same at trial 600 and at trial 30,000. Up to ``2 * window`` finished trials the view is the whole
study, and TPE proposes what it would have proposed alone.
"""

from __future__ import annotations

from typing import Any, Sequence

import optuna
from optuna.distributions import BaseDistribution
from optuna.trial import FrozenTrial, TrialState

#: TPE's good group is at most 25 trials (``optuna.samplers._tpe.sampler.default_gamma``)
KEEP_BEST = 25
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)


def unseen(trials: Sequence[FrozenTrial], seen: set[int]) -> list[FrozenTrial]:
    """The trials of ``trials`` whose numbers are not in ``seen``, in order. ``trials`` are finished
    trials in order of number (a study's, which only grow) and ``seen`` holds numbers of some of them, so
    as many are new as the counts differ: they are looked for from the end, where trials finish, and a
    search of thousands of trials does not walk them all at every trial."""
    missing = len(trials) - len(seen)
    new: list[FrozenTrial] = []
    for t in reversed(trials):
        if len(new) >= missing:
            break
        if t.number not in seen:
            new.append(t)
    return new[::-1]


class RecentTrialsTPE(optuna.samplers.BaseSampler):
    """A ``TPESampler(**tpe_options)`` asked about the best ``KEEP_BEST`` finished trials and the latest
    ones, between ``window`` and ``2 * window`` trials in all (the view is extended by each new trial
    and rebuilt when it doubles). Single-objective studies only (TPE's good group is by value).

    TPE's constant liar (the running trials of other workers counted as bad ones) is off: the view
    holds finished trials only. Workers sharing a study may then propose a candidate another worker
    is evaluating; the search reuses a finished twin's result, so this costs an estimate, not a trial."""

    def __init__(self, window: int = 256, **tpe_options) -> None:
        if window <= KEEP_BEST:
            raise ValueError(f"window must be more than {KEEP_BEST} trials")
        if tpe_options.get("constant_liar"):
            raise ValueError("the view holds finished trials only: constant_liar cannot be used")
        self.tpe = optuna.samplers.TPESampler(**{**tpe_options, "constant_liar": False})
        self.window = window
        self._view: optuna.Study | None = None
        self._storage: optuna.storages.InMemoryStorage | None = None
        self._in_view: set[int] = set()    # the trials in the view
        self._seen: set[int] = set()       # the finished trials the view was made from (in it or left out)

    @property
    def trials_in_view(self) -> list[int]:
        """The numbers (in the study) of the trials TPE reads now."""
        return sorted(self._in_view)

    # -- the view -------------------------------------------------------------------------------------
    def view(self, study: optuna.Study) -> optuna.Study:
        """The study TPE reads: an in-memory copy of the trials it needs (parameters, values, state)."""
        finished = study.get_trials(deepcopy=False, states=FINISHED)
        new = unseen(finished, self._seen)
        if self._view is None or len(self._in_view) + len(new) > 2 * self.window:
            self._rebuild(study, finished)
        elif new:
            self._add(new)
        self._seen.update(t.number for t in new)
        return self._view

    def _rebuild(self, study: optuna.Study, finished: list[FrozenTrial]) -> None:
        recent = finished[-(self.window - KEEP_BEST):] if len(finished) > self.window else finished
        complete = [t for t in finished if t.state == TrialState.COMPLETE and t.values]
        sign = 1.0 if study.direction == optuna.study.StudyDirection.MINIMIZE else -1.0
        best = sorted(complete, key=lambda t: sign * t.values[0])[:KEEP_BEST]
        chosen = {t.number: t for t in [*best, *recent]}
        # a fresh in-memory storage: its study id is always the first one, as TPE's search-space memo requires
        self._storage = optuna.storages.InMemoryStorage()
        self._view = optuna.create_study(storage=self._storage, directions=study.directions,
                                         sampler=optuna.samplers.RandomSampler())
        self._in_view = set()
        self._add([chosen[n] for n in sorted(chosen)])

    def _add(self, trials: Sequence[FrozenTrial]) -> None:
        view = self._view
        view.add_trials([optuna.trial.create_trial(
            state=t.state, params=t.params, distributions=t.distributions, values=t.values,
            intermediate_values=t.intermediate_values) for t in trials])
        self._in_view.update(t.number for t in trials)
        # a Study keeps the trials TPE read last; a new one over the same storage reads them afresh
        self._view = optuna.load_study(study_name=view.study_name, storage=self._storage,
                                       sampler=optuna.samplers.RandomSampler())

    # -- BaseSampler: TPE on the view ---------------------------------------------------------------
    def infer_relative_search_space(self, study: optuna.Study, trial: FrozenTrial) -> dict[str, BaseDistribution]:
        return self.tpe.infer_relative_search_space(self.view(study), trial)

    def sample_relative(self, study: optuna.Study, trial: FrozenTrial,
                        search_space: dict[str, BaseDistribution]) -> dict[str, Any]:
        return self.tpe.sample_relative(self.view(study), trial, search_space)

    def sample_independent(self, study: optuna.Study, trial: FrozenTrial, param_name: str,
                           param_distribution: BaseDistribution) -> Any:
        return self.tpe.sample_independent(self.view(study), trial, param_name, param_distribution)

    def before_trial(self, study: optuna.Study, trial: FrozenTrial) -> None:
        self.tpe.before_trial(study, trial)

    def after_trial(self, study: optuna.Study, trial: FrozenTrial, state: TrialState,
                    values: Sequence[float] | None) -> None:
        self.tpe.after_trial(study, trial, state, values)

    def reseed_rng(self) -> None:
        self.tpe.reseed_rng()
