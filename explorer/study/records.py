"""What a study stores in Optuna, typed: a trial's record (:class:`TrialRecord`) and the study's own
(:class:`StudyRecord`). This is the one module that names the stored keys.

Each field is one Optuna user attribute, so a study stays readable by Optuna's own tools (the dashboard,
``optuna.load_study``) and a running trial can record what it knows as it goes (its costs first, its
metrics when its evaluation ends). Writes go through :func:`record` / :func:`record_study`, which check
each value against the schema; reads go through :func:`trial_record` / :func:`study_record`, which
validate what was stored and turn a damaged or newer record into one line (UserError)."""

from __future__ import annotations

import math
import weakref
from typing import Any, Optional

import optuna
from pydantic import BaseModel, ConfigDict, ValidationError

from explorer.errors import UserError

RECORD_VERSION = 1          # bumped when a field changes meaning; added fields keep the version
VERSION_KEY = "record_version"
PathMetrics = list[dict[str, Any]]


class Measured(BaseModel):
    """Where a retrained network's per-path figures come from: the first ``frames`` of a split of
    ``data``, at ``input_size`` (the deployment size)."""

    data: str
    split: str
    frames: int
    input_size: tuple[int, int]


class Retraining(BaseModel):
    """A network retrained stand-alone with the finalists' ``recipe`` (a finalist, a baseline or a
    dedicated network of the envelope): which search trial estimated it, and at what value."""

    model_config = ConfigDict(extra="allow")

    recipe: dict[str, Any]
    estimate_trial: Optional[int] = None
    estimated: Optional[float] = None
    path: Optional[int] = None        # a dedicated network of the envelope: the one path it was trained for


class Shipped(BaseModel):
    """What was left out of a trial's network for shipping (explorer.model.shipped): the candidate that
    ships, the trained network's path behind each of its paths, and each exit dropped with why. The
    trial's costs and per-path figures are those of the shipped network."""

    candidate: dict[str, Any]
    trained_paths: list[int]
    dropped: list[dict[str, Any]]


class TrialRecord(BaseModel):
    """Everything a trial stores. A sampled trial holds its candidate, costs and estimated metrics; a
    retrained one holds ``finalist`` (or ``envelope``) and ``measured`` too; a baseline is tagged by
    ``baseline``; a trial that did not complete says why (``rejected``, ``pruned``, ``not_run``,
    ``duplicate_of``)."""

    model_config = ConfigDict(frozen=True, extra="ignore")

    record_version: int = RECORD_VERSION
    baseline: Optional[str] = None          # a baseline's name ("paper", ...): compared, never the winner
    reference: Optional[str] = None         # a reference network outside every space
    candidate: Optional[dict[str, Any]] = None
    candidate_key: Optional[str] = None
    params: Optional[list[int]] = None      # per path, path 0 (the LiDAR-only path) first
    macs: Optional[list[int]] = None
    latency_ms: Optional[list[float]] = None
    energy_j: Optional[list[float]] = None
    workloads: Optional[dict[str, Any]] = None   # compact per-layer workloads: re-costing on any device
    path_metrics: Optional[PathMetrics] = None
    path_metrics_fp32: Optional[PathMetrics] = None
    int8_graphs: Optional[list[str]] = None
    quantization: Optional[dict[str, Any]] = None
    evaluator: Optional[dict[str, Any]] = None
    train: Optional[dict[str, Any]] = None
    losses: Optional[dict[str, float]] = None   # budget spec -> anytime loss
    weights_artifact: Optional[str] = None
    rejected: Optional[str] = None
    pruned: Optional[str] = None
    not_run: Optional[str] = None           # asked past --trials (another worker's trial reached it): not counted
    duplicate_of: Optional[int] = None
    retry_of: Optional[int] = None
    finalist: Optional[Retraining] = None
    envelope: Optional[Retraining] = None
    measured: Optional[Measured] = None
    shipped: Optional[Shipped] = None       # exits dropped for shipping: costs and figures are the shipped network's

    @property
    def shipped_candidate(self) -> Optional[dict[str, Any]]:
        """The candidate as shipped: ``candidate`` less the exits dropped (explorer.model.shipped)."""
        return self.shipped.candidate if self.shipped is not None else self.candidate

    @property
    def retraining(self) -> Retraining | None:
        return self.finalist or self.envelope

    @property
    def is_retrained(self) -> bool:
        """A finalist or baseline retrained with the study's longer recipe (see explorer.study.finalists)."""
        return self.finalist is not None

    @property
    def is_envelope(self) -> bool:
        return self.envelope is not None

    @property
    def is_scored(self) -> bool:
        """Carries what re-scoring needs (per-path metrics and workloads)."""
        return self.path_metrics is not None and self.workloads is not None

    @property
    def is_estimate(self) -> bool:
        """A search trial's estimate (not a retraining), scored."""
        return self.is_scored and self.finalist is None and self.envelope is None

    @property
    def figures(self) -> str:
        """"measured" for a retrained network, "estimate" for a search trial."""
        return "measured" if self.retraining is not None else "estimate"

    @property
    def evaluator_name(self) -> str:
        return (self.evaluator or {}).get("evaluator", "proxy")

    @property
    def precision(self) -> str:
        return (self.candidate or {}).get("precision", "fp32")

    def losses_of(self, metric: str | None = None) -> list[float]:
        """Each path's ``metric``; by default its :attr:`error_metric`."""
        metric = metric or self.error_metric
        return [float(m[metric]) if m.get(metric) is not None else math.nan for m in self.path_metrics or []]

    @property
    def error_metric(self) -> str:
        """What its figures show as each path's error: RMSE where its frames had depth, else the
        photometric error (a study on a recording without depth)."""
        metrics = self.path_metrics or []
        has_rmse = any(m.get("rmse") is not None and math.isfinite(m["rmse"]) for m in metrics)
        return "rmse" if has_rmse or not any(m.get("photometric") is not None for m in metrics) else "photometric"


class PlanRecord(BaseModel):
    """A ``--time-limit`` run's plan as the study stored it (:class:`explorer.study.planning.Plan`): what
    the run was sized to, and what changed as it ran. A field a plan left out reads as nothing planned."""

    model_config = ConfigDict(frozen=True, extra="ignore")

    limit_s: float = 0.0
    supernet_steps: int = 0
    supernet_s: float = 0.0
    sampling_s: float = 0.0
    finalists: int = 0
    finalist_steps: int = 0
    retrain_jobs: int = 0
    retrain_s: float = 0.0
    changes: tuple[str, ...] = ()
    trial_s: float = 0.0
    tune: str = ""
    fits: bool = True
    not_retrained: int = 0


class StudyRecord(BaseModel):
    """What a study stores about itself: its configuration (read as a checked SearchConfig by
    explorer.study.config.study_config), the space and device profile it was created with, its plan
    and runs."""

    model_config = ConfigDict(frozen=True, extra="ignore")

    config: Optional[dict[str, Any]] = None
    explorer_version: Optional[str] = None
    space_yaml: Optional[str] = None
    device_profile: Optional[dict[str, Any]] = None
    created: Optional[str] = None
    baselines_not_estimated: dict[str, str] = {}
    plan: Optional[PlanRecord] = None
    runs: list[dict[str, Any]] = []
    artifacts_dir: Optional[str] = None
    supernet: Optional[str] = None


TRIAL_FIELDS = frozenset(TrialRecord.model_fields)
STUDY_FIELDS = frozenset(StudyRecord.model_fields)
_cache: dict[int, tuple[optuna.trial.FrozenTrial, tuple, TrialRecord]] = {}


def trial_record(trial: optuna.trial.FrozenTrial | optuna.Trial) -> TrialRecord:
    """``trial``'s record, validated. A finished trial's record is read once (a study's tables ask for
    it many times); a record of a newer version or a damaged one is one line."""
    attrs = trial.user_attrs
    stamp = (len(attrs), getattr(trial, "state", None))
    cached = _cache.get(id(trial))
    if cached is not None and cached[0] is trial and cached[1] == stamp:
        return cached[2]
    version = attrs.get(VERSION_KEY, RECORD_VERSION)
    if isinstance(version, int) and not isinstance(version, bool) and version > RECORD_VERSION:
        raise UserError(f"trial {trial.number} was stored by a newer anytime-explorer (record version {version}): "
                        "upgrade anytime-explorer to read this study")
    try:
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise ValueError(f"{VERSION_KEY}: {version!r} is no version")
        out = TrialRecord.model_validate(attrs)
        if getattr(trial, "state", None) == optuna.trial.TrialState.COMPLETE:
            _check_figures(out)
    except ValidationError as exc:
        raise UserError(f"trial {trial.number}'s stored record is damaged ({_first_error(exc)}): "
                        "run the trial again or restore the study's storage") from None
    except ValueError as exc:
        raise UserError(f"trial {trial.number}'s stored record is damaged ({exc}): "
                        "run the trial again or restore the study's storage") from None
    if isinstance(trial, optuna.trial.FrozenTrial) and trial.state.is_finished():
        if len(_cache) > 100_000:
            _cache.clear()
        _cache[id(trial)] = (trial, stamp, out)
    return out


def _check_figures(rec: TrialRecord) -> None:
    """A completed trial's figures are not negative nor infinite (errors, times, energies, losses): a
    value stored by an edit would rank a network nowhere, or first. A path's metric may be NaN or null
    (not measured: no depth in self-supervised frames); the study's own metric is checked where it is
    read (:func:`explorer.study.results.trial_losses`). ValueError names the first that is wrong."""
    for i, metrics in enumerate(rec.path_metrics or []):
        for key, value in metrics.items():
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if number and not math.isnan(value) and not 0 <= value < math.inf:
                raise ValueError(f"path {i}'s {key} is {value}")
    named = {"latency_ms": rec.latency_ms or [], "energy_j": rec.energy_j or [],
             "losses": list((rec.losses or {}).values())}
    for key, values in named.items():
        bad = [v for v in values if not 0 <= v < math.inf]
        if bad:
            raise ValueError(f"{key} holds {bad[0]}")


def record_values(**fields: Any) -> dict[str, Any]:
    """``fields`` checked against the schema, as the JSON values a trial stores (for trials created
    whole, e.g. ``optuna.trial.create_trial(user_attrs=...)``)."""
    fields = {k: v for k, v in fields.items() if v is not None}     # an absent field reads as None
    unknown = set(fields) - TRIAL_FIELDS
    if unknown:
        raise TypeError(f"not fields of a trial record: {sorted(unknown)}")
    checked = TrialRecord.model_validate(fields)
    out = checked.model_dump(mode="json", include=set(fields))
    out.setdefault(VERSION_KEY, RECORD_VERSION)
    return out


#: the live trials that carry the record version already: a live trial's ``user_attrs`` is a deep copy
#: of everything it stored (its workloads: about 1 ms a read), and a trial records several times
_versioned: "weakref.WeakSet[optuna.Trial]" = weakref.WeakSet()


def record(trial: optuna.Trial, **fields: Any) -> None:
    """Stores ``fields`` on a live ``trial`` (each checked against :class:`TrialRecord`)."""
    values = record_values(**fields)
    live = isinstance(trial, optuna.Trial)
    if (live and trial in _versioned) or VERSION_KEY in trial.user_attrs:
        del values[VERSION_KEY]
    for key, value in values.items():
        trial.set_user_attr(key, value)
    if live:
        _versioned.add(trial)


def study_record(study: optuna.Study) -> StudyRecord:
    try:
        return StudyRecord.model_validate(study.user_attrs)
    except ValidationError as exc:
        raise UserError(f"study '{study.study_name}''s stored settings are damaged ({_first_error(exc)}): "
                        "restore the study's storage") from None


def record_study(study: optuna.Study, **fields: Any) -> None:
    """Stores ``fields`` on ``study`` (each checked against :class:`StudyRecord`)."""
    unknown = set(fields) - STUDY_FIELDS
    if unknown:
        raise TypeError(f"not fields of a study record: {sorted(unknown)}")
    checked = StudyRecord.model_validate(fields)
    for key, value in checked.model_dump(mode="json", include=set(fields)).items():
        study.set_user_attr(key, value)


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ()))
    return f"{where}: {err.get('msg', 'invalid')}"
