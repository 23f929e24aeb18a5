"""Interrupted work is tried again; work that failed by its own fault is a result.

A trial is *interrupted* when the process running it stopped under it:

- killed (``kill -9``, the OOM killer, a reboot): found RUNNING when a search resumes on local
  storage (SQLite, journal file), where no other process can be working on the study;
- stopped with Ctrl-C (``KeyboardInterrupt`` in the objective);
- stopped by a write the machine refused (a full disk, a folder made read-only): enqueued again on resume;
- a worker whose heartbeat stopped (RDB storage such as PostgreSQL): another worker fails the trial
  after the grace period, through Optuna's heartbeat mechanism.

An interrupted trial is enqueued again with the same parameters and the same user attributes it was
given (a baseline stays that baseline), at most ``max_retries`` times in a row. The retry records
``retry_of`` (user attribute: the trial it retries) and Optuna's ``failed_trial`` / ``retry_history``
system attributes, as ``optuna.storages.RetryHeartbeatStaleTrialCallback`` writes them (so its
``retried_trial_number`` and ``retry_history`` read ours). A trial whose objective raised (a NaN loss,
an error in training) records ``fail_reason`` and is never retried: that is a result. Interrupted
trials do not count toward ``--trials``; their retries do.
"""

from __future__ import annotations

import warnings
from typing import Any, Callable, Sequence

import optuna
from optuna.trial import FrozenTrial, TrialState

from explorer.errors import refused_write
from explorer.study.records import VERSION_KEY, record, record_values, trial_record

INTERRUPTED = "interrupted"
KILLED = "interrupted (process killed)"      # fail_interrupted_trials writes this
CTRL_C = "interrupted (Ctrl-C)"
REFUSED_WRITE = "interrupted (a write the machine refused)"   # a full disk: the resume tries it again
_STUDY_MARK = "interrupted:"                   # study system attr "interrupted:<number>" -> reason
INPUT_ATTRS = "input_attrs"                    # trial system attr: the user attrs it was started with


def error_text(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__


def interrupted_trials(study: optuna.Study, trials: Sequence[FrozenTrial] | None = None) -> dict[int, str]:
    """Trial number -> how it was interrupted, for the FAIL trials among ``trials`` (default: all of the
    study's) that were interrupted rather than failed by their own fault."""
    if trials is None:
        trials = study.get_trials(deepcopy=False, states=(TrialState.FAIL,))
    out: dict[int, str] = {}
    marks: dict[int, str] | None = None
    for t in trials:
        if t.state != TrialState.FAIL:
            continue
        reason = str(t.system_attrs.get("fail_reason", ""))
        if reason.startswith(INTERRUPTED):
            out[t.number] = reason
            continue
        if marks is None:  # heartbeat-failed trials are finished before we see them: marked on the study
            attrs = study._storage.get_study_system_attrs(study._study_id)
            marks = {int(k[len(_STUDY_MARK):]): str(v) for k, v in attrs.items() if k.startswith(_STUDY_MARK)}
        if t.number in marks:
            out[t.number] = marks[t.number]
    return out


def retries_by_origin(trials: Sequence[FrozenTrial]) -> dict[int, FrozenTrial]:
    """Interrupted trial number -> the trial that retries it."""
    return {trial_record(t).retry_of: t for t in trials if trial_record(t).retry_of is not None}


def enqueue_retry(study: optuna.Study, trial: FrozenTrial, max_retries: int) -> int | None:
    """Enqueues ``trial`` again (same parameters, the user attributes it was started with) and returns
    the new trial's number; None when it has already been interrupted more than ``max_retries`` times
    in a row."""
    history = [*trial.system_attrs.get("retry_history", []), trial.number]
    if len(history) > max_retries:
        return None
    keys = trial.system_attrs.get(INPUT_ATTRS)
    if keys is None:  # started before input attributes were recorded: the baseline tag is the input
        keys = ["baseline"]
    given = {k: trial.user_attrs[k] for k in keys if k in trial.user_attrs and k not in ("retry_of", VERSION_KEY)}
    user_attrs = record_values(**given, retry_of=trial.number)
    system_attrs: dict[str, Any] = {"failed_trial": history[0], "retry_history": history}
    if "fixed_params" in trial.system_attrs:
        system_attrs["fixed_params"] = trial.system_attrs["fixed_params"]
    return _enqueue_copy(study, trial, user_attrs, system_attrs)


def _enqueue_copy(study: optuna.Study, trial: FrozenTrial, user_attrs: dict, system_attrs: dict) -> int:
    """Enqueues a trial with ``trial``'s parameters and the given attributes; returns its number."""
    template = optuna.trial.create_trial(state=TrialState.WAITING, params=trial.params,
                                         distributions=trial.distributions, user_attrs=user_attrs,
                                         system_attrs=system_attrs)
    trial_id = study._storage.create_new_trial(study._study_id, template_trial=template)
    return study._storage.get_trial_number_from_id(trial_id)


def retry_interrupted(study: optuna.Study, max_retries: int) -> tuple[dict[int, int], list[int]]:
    """Enqueues again every interrupted trial that has no retry yet. Returns ({interrupted: retry},
    [interrupted trials not retried because they reached ``max_retries``]). Only call where no other
    worker can be doing the same (a resume on local storage): otherwise a trial could be retried twice."""
    trials = study.get_trials(deepcopy=False)
    by_number = {t.number: t for t in trials}
    done = retries_by_origin(trials)
    retried, given_up = {}, []
    for number in sorted(interrupted_trials(study, trials)):
        if number in done:
            continue
        new = enqueue_retry(study, by_number[number], max_retries)
        if new is None:
            given_up.append(number)
        else:
            retried[number] = new
    return retried, given_up


def resume_interrupted(study: optuna.Study, max_retries: int) -> tuple[int, dict[int, int], list[int]]:
    """On resume with local storage (nobody else can be running): marks RUNNING trials as interrupted
    (FAIL), then enqueues every interrupted trial again. Returns (trials marked, retried, given up)."""
    failed = fail_interrupted_trials(study)
    return (failed, *retry_interrupted(study, max_retries))


class RetryStaleTrials:
    """``heartbeat_stale_trial_callback`` of an RDB storage: a trial whose worker stopped sending
    heartbeats (Optuna has just failed it) is marked interrupted and enqueued again. Optuna calls it in
    the one worker that failed the trial, so a stale trial is retried once."""

    def __init__(self, max_retries: int, grace_period_s: int) -> None:
        self.max_retries = max_retries
        self.grace_period_s = grace_period_s

    def __call__(self, study: optuna.Study, trial: FrozenTrial) -> None:
        reason = f"interrupted (no heartbeat for {self.grace_period_s} s: its worker stopped)"
        # a finished trial's attributes cannot change any more: the mark goes on the study
        study._storage.set_study_system_attr(study._study_id, f"{_STUDY_MARK}{trial.number}", reason)
        enqueue_retry(study, trial, self.max_retries)


def _counts(trial: FrozenTrial) -> bool:
    rec = trial_record(trial)
    return rec.retraining is None and rec.not_run is None


def counted_trials(study: optuna.Study) -> int:
    """Finished trials that count toward ``--trials``: an interrupted one does not (its retry does),
    nor a finalist's or a dedicated network's retraining (they are not sampled trials), nor one asked
    past the limit and not run (``not_run``)."""
    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL))
    done = [t for t in done if _counts(t)]
    return len(done) - len(interrupted_trials(study, done))


def _running_trials(study: optuna.Study, before: int | None = None) -> list[FrozenTrial]:
    """The sampled trials running now (numbered below ``before`` if given)."""
    return [t for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
            if _counts(t) and (before is None or t.number < before)]


class StopAfterTrials:
    """Like ``optuna.study.MaxTrialsCallback``, counting what :func:`counted_trials` counts, and the
    trials other workers are running: a worker does not start a trial that theirs will make one too many
    (``--workers 2 --trials 2`` runs two trials, not three). Two workers finishing at once can both
    start one more; :func:`guarded` stops the later of the two before it does any work."""

    def __init__(self, n_trials: int) -> None:
        self.n_trials = n_trials

    def __call__(self, study: optuna.Study, trial: FrozenTrial) -> None:
        if counted_trials(study) + len(_running_trials(study)) >= self.n_trials:
            study.stop()


def _past_the_limit(trial: optuna.Trial, n_trials: int) -> bool:
    """True when the trials that count, with the running ones asked before ``trial``, already reach
    ``n_trials``: trial numbers order the workers' asks, so of two trials asked at once only the later
    one is past the limit, whichever worker looks first."""
    study = trial.study
    return counted_trials(study) + len(_running_trials(study, before=trial.number)) >= n_trials


def _give_back(trial: optuna.Trial, n_trials: int) -> None:
    """Marks ``trial`` as not run (:class:`StopAfterTrials` then stops the worker); an enqueued trial
    (a baseline, a retry) goes back to the queue with its parameters and attributes, so that a longer
    search still runs it."""
    frozen = trial.study._storage.get_trial(trial._trial_id)
    if "fixed_params" in frozen.system_attrs:
        _enqueue_copy(trial.study, frozen, frozen.user_attrs, frozen.system_attrs)
    record(trial, not_run=f"not run: the study's {n_trials} trials were reached by other workers' trials")


def guarded(objective: Callable[[optuna.Trial], Any], max_retries: int,
            n_trials: int | None = None) -> Callable[[optuna.Trial], Any]:
    """``objective`` for ``study.optimize``, recording what a retry needs and why a trial failed:
    the user attributes it was started with; ``fail_reason`` when it raises (its own fault: not
    retried); on Ctrl-C, "interrupted (Ctrl-C)" and a retry enqueued at once. With ``n_trials``, a
    trial asked past the limit (two workers asked at once) is pruned before any work, marked
    ``not_run`` and not counted."""
    def run(trial: optuna.Trial):
        storage, tid = trial.study._storage, trial._trial_id
        if n_trials is not None and _past_the_limit(trial, n_trials):
            _give_back(trial, n_trials)
            raise optuna.TrialPruned()
        storage.set_trial_system_attr(tid, INPUT_ATTRS, sorted(trial.user_attrs))
        try:
            return objective(trial)
        except optuna.TrialPruned:
            raise
        except KeyboardInterrupt:
            storage.set_trial_system_attr(tid, "fail_reason", CTRL_C)
            enqueue_retry(trial.study, storage.get_trial(tid), max_retries)
            raise
        except Exception as exc:
            refused = refused_write(exc)   # a full disk, a read-only folder: not the candidate's fault, tried again
            storage.set_trial_system_attr(tid, "fail_reason", error_text(exc) if refused is None else
                                          f"{REFUSED_WRITE}: {error_text(refused)}")
            raise
    return run


def rdb_retry_kwargs(max_retries: int | None, grace_period_s: int) -> dict:
    """The keyword that installs :class:`RetryStaleTrials` on an ``RDBStorage`` (its name changed in
    Optuna 4.9)."""
    if max_retries is None:
        return {}
    import inspect
    params = inspect.signature(optuna.storages.RDBStorage.__init__).parameters
    name = "heartbeat_stale_trial_callback" if "heartbeat_stale_trial_callback" in params else "failed_trial_callback"
    return {name: RetryStaleTrials(max_retries, grace_period_s)}


def set_objective_names(study: optuna.Study, names: list[str]) -> None:
    """Names the objectives (optuna-dashboard and Optuna's plots show them instead of "Objective 0")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if study.metric_names != names:
            study.set_metric_names(names)


def fail_interrupted_trials(study: optuna.Study) -> int:
    """Marks RUNNING trials as FAIL, interrupted (their process died, e.g. kill -9). Only call when no
    other worker can be running on this study. ``explorer.study.retry.resume_interrupted`` also retries them."""
    n = 0
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        study._storage.set_trial_system_attr(t._trial_id, "fail_reason", "interrupted (process killed)")
        study._storage.set_trial_state_values(t._trial_id, optuna.trial.TrialState.FAIL)
        n += 1
    return n
