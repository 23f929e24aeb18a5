"""Every trial is scored as the network that ships: its exits no better than an earlier path left out,
its costs and per-path figures those of what ships, unless --keep-every-exit."""

import optuna
import pandas as pd
import pytest

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost
from explorer.space import Candidate
from explorer.study.objective import Objective
from explorer.study.records import trial_record
from explorer.study.results import trial_anytime_loss
from explorer.study.search import SearchConfig
from explorer.supernet.evaluators import Evaluation
from conftest import TINY_DATA

TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=2,
            batch_size=8, val_limit=16, evaluator="proxy", finalists=0, baselines=(), pruning=False,
            keep_weights=False)


class WorseSecondPath:
    """An evaluator whose path 1 is less accurate than the scan (path 0), every other path better than
    the one before it."""

    name = "proxy"

    def __call__(self, candidate, checkpoint=None, report=None) -> Evaluation:
        rmse = [1.0, 1.2] + [0.9 - 0.1 * i for i in range(candidate.num_paths - 2)]
        metrics = pd.DataFrame({"path": range(candidate.num_paths), "rmse": rmse, "abs_rel": rmse})
        return Evaluation(metrics, {"evaluator": "proxy", "seconds": 0.0, "steps": 0, "images_per_second": 0.0})


def _trial(keep_every_exit: bool):
    context = SearchConfig(study="shipping", keep_every_exit=keep_every_exit, **TINY).resolve()
    objective = Objective(context, None)
    objective.evaluator = WorseSecondPath()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    study.optimize(objective, n_trials=1)
    return context, study.trials[0]


@pytest.fixture(scope="module")
def shipped():
    return _trial(keep_every_exit=False)


def test_a_trial_is_scored_as_the_network_that_ships_without_the_exit_worse_than_the_scan(shipped):
    context, trial = shipped
    rec = trial_record(trial)
    trained = Candidate.from_dict(rec.candidate)
    ships = Candidate.from_dict(rec.shipped_candidate)
    assert [d["path"] for d in rec.shipped.dropped] == [1]
    assert ships.num_paths == trained.num_paths - 1 == len(rec.path_metrics)
    assert rec.shipped.trained_paths == [0, *range(2, trained.num_paths)]
    assert [m["rmse"] for m in rec.path_metrics] == [1.0] + [0.9 - 0.1 * i for i in range(trained.num_paths - 2)]
    costs = candidate_cost(ships, (64, 64)).path_latency_ms(context.device)
    assert rec.latency_ms == pytest.approx(costs)
    # the later paths are ready sooner than in the trained network: the dropped head is not computed
    full = candidate_cost(trained, (64, 64)).path_latency_ms(context.device)
    assert all(s < f for s, f in zip(costs[1:], full[2:]))
    expected = anytime_loss(costs, [m["rmse"] for m in rec.path_metrics], context.budgets[0])
    assert trial.values[0] == pytest.approx(expected)
    assert trial_anytime_loss(trial, context.device, context.budgets[0]) == pytest.approx(expected)


def test_keep_every_exit_scores_the_network_as_trained():
    context, trial = _trial(keep_every_exit=True)
    rec = trial_record(trial)
    trained = Candidate.from_dict(rec.candidate)
    assert rec.shipped is None and len(rec.path_metrics) == trained.num_paths
    assert rec.latency_ms == pytest.approx(candidate_cost(trained, (64, 64)).path_latency_ms(context.device))
