"""One view of a stored study, built once for whatever reads it (the report and its figures, the envelope,
the search's summary, re-scoring, an export): the study's resolved context (its settings, and the space
and device profile it stored when it was made), its own record, and its trials as the view read them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import optuna

from explorer.cost.devices import DeviceProfile, get_device
from explorer.study.config import COMPARISON_DEVICES, SearchConfig, StudyContext, study_context
from explorer.study.records import StudyRecord, study_record


@dataclass(frozen=True)
class StudyView:
    """A study as its readers see it. Made by :func:`study_view`; a reader that changes the study (adds
    trials, as the envelope's retraining does) leaves the next reader a view made again."""

    study: optuna.Study
    context: StudyContext
    record: StudyRecord
    trials: tuple[optuna.trial.FrozenTrial, ...]   # every trial, finished or not (a queued baseline is named)

    @property
    def config(self) -> SearchConfig:
        """The settings the study stored (those of a study made outside ``explorer search``: the defaults)."""
        return self.context.config

    @property
    def name(self) -> str:
        return self.study.study_name

    def devices(self, others: Sequence[str] | None = None) -> list[DeviceProfile]:
        """The study's own device profile (as it stored it), then the ``others`` asked for (by default
        :data:`~explorer.study.config.COMPARISON_DEVICES`), each once."""
        primary = self.context.device
        return [primary] + [get_device(d) for d in (others or COMPARISON_DEVICES) if d != primary.name]


def study_view(study: optuna.Study) -> StudyView:
    """The view of ``study`` as it is now; a damaged stored context (settings, space, device profile) is
    one line, before anything is read or written."""
    context = study_context(study)
    return StudyView(study, context, study_record(study), tuple(study.get_trials(deepcopy=False)))
