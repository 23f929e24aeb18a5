"""The search's sampler: TPE over the best and the latest trials, the same as TPE on a short study."""

import warnings

import optuna
import pytest

from explorer.study.sampling import KEEP_BEST, RecentTrialsTPE, unseen


OPTIONS = dict(seed=3, n_startup_trials=5, multivariate=True, group=True)


def _tpe() -> optuna.samplers.TPESampler:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.TPESampler(**OPTIONS, constant_liar=False)


def _windowed(window: int) -> RecentTrialsTPE:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return RecentTrialsTPE(window=window, **OPTIONS)


def _objective(trial: optuna.Trial) -> float:
    x = trial.suggest_float("x", -3, 3)
    kind = trial.suggest_categorical("kind", ["a", "b"])
    if kind == "b":   # a conditional dimension, as the space's LiDAR branch
        x += trial.suggest_int("shift", 0, 4) - 2
    if trial.number % 7 == 6:
        raise optuna.TrialPruned()   # rejected candidates: pruned, without a value
    return (x - 1.0) ** 2


def _run(sampler, trials: int) -> optuna.Study:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=sampler)
    study.optimize(_objective, n_trials=trials)
    return study


def test_on_a_short_study_it_proposes_what_tpe_proposes():
    plain = _run(_tpe(), 45)
    windowed = _run(_windowed(30), 45)   # 45 <= 2 * 30: the view is the whole study
    assert [t.params for t in windowed.trials] == [t.params for t in plain.trials]


def test_on_a_long_study_it_reads_the_best_and_the_latest_trials_only():
    sampler = _windowed(40)
    study = _run(sampler, 200)
    in_view = sampler.trials_in_view
    assert len(in_view) <= 80
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    best = sorted(complete, key=lambda t: t.value)[:KEEP_BEST]
    finished = [t.number for t in study.trials if t.state.is_finished()]
    assert {t.number for t in best} <= set(in_view)          # TPE's good group: as over the whole study
    assert finished[-(40 - KEEP_BEST):][0] >= min(set(in_view) - {t.number for t in best})
    assert study.best_value < 0.05                           # it still finds the minimum


def test_the_view_grows_by_each_new_trial_and_is_rebuilt_only_when_it_doubles():
    sampler, sizes = _windowed(40), []
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=sampler)
    study.optimize(_objective, n_trials=200, callbacks=[lambda s, t: sizes.append(len(sampler.trials_in_view))])
    shrinks = sum(1 for a, b in zip(sizes, sizes[1:]) if b < a)
    assert 1 <= shrinks <= 200 // 40 and max(sizes) <= 80
    assert {b - a for a, b in zip(sizes, sizes[1:]) if b >= a} == {1}   # each finished trial joins it


def test_a_window_smaller_than_the_good_group_or_a_constant_liar_is_refused():
    with pytest.raises(ValueError):
        RecentTrialsTPE(window=KEEP_BEST)
    with pytest.raises(ValueError):
        RecentTrialsTPE(constant_liar=True)


def test_the_trials_not_seen_yet_are_found_however_late_they_finished():
    study = _run(optuna.samplers.RandomSampler(seed=0), 12)
    trials = study.get_trials(deepcopy=False)
    seen = {t.number for t in trials if t.number not in (2, 10)}   # trial 2 finished late, 10 is new
    assert [t.number for t in unseen(trials, seen)] == [2, 10]
    assert unseen(trials, {t.number for t in trials}) == []
    assert [t.number for t in unseen(trials, set())] == list(range(12))
