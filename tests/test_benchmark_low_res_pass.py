"""bench_low_res_pass (experiments/low_res_pass.py) chains a network run at a lower size before one at the
deployment size, and scores the first at the deployment size."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from experiments.lib.retraining import Retrained
from experiments.low_res_pass import chained, resolve_first, upsampled_errors

from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import paper_candidate
from explorer.study.config import SearchConfig
from explorer.training.train import evaluate

from conftest import TINY_DATA

CONTEXT = SearchConfig(study="s", space="anytime_depth", device="tx2").resolve()
LOW, FULL = (112, 112), (224, 224)


def _costs(candidate, size):
    return candidate_cost(candidate, size).path_costs(CONTEXT.device, CONTEXT.budgets[0].kind)


def test_the_second_network_starts_when_the_first_is_done_and_keeps_only_exits_below_it():
    paper = paper_candidate()                                   # paths: scan, exit_0, exit_1, exit_2, exit_4
    first_errors = [0.9, 0.40, 0.35, 0.30, 0.28]
    then = Retrained(paper, [float(c) for c in _costs(paper, FULL)], [0.9, 0.45, 0.29, 0.25, 0.20])
    chain = chained(0.8, paper, first_errors, then, LOW, FULL, CONTEXT)
    first = _costs(paper, LOW)
    # the scan, every path of the first (each below the one before), then the second's paths below 0.28 only
    assert chain.errors == [0.8, 0.40, 0.35, 0.30, 0.28, 0.25, 0.20]
    assert chain.costs[:5] == pytest.approx([0.0, *first[1:]])
    shipped = dataclasses.replace(paper, exits=(2, 4))         # exit_0 and exit_1 left out: not below 0.28
    assert chain.costs[5:] == pytest.approx([first[-1] + c for c in _costs(shipped, FULL)[1:]])
    assert chain.costs == sorted(chain.costs)


def test_one_network_alone_is_shipped_as_the_study_ships_it():
    paper = paper_candidate()
    chain = chained(0.5, paper, [0.9, 0.6, 0.45, 0.47, 0.40], None, LOW, FULL, CONTEXT)
    assert chain.errors == [0.5, 0.45, 0.40]                    # exit_0 (not below the scan) and exit_2 dropped
    ms = candidate_cost(dataclasses.replace(paper, exits=(1, 4)), LOW).path_costs(get_device("tx2"), "time")
    assert chain.tx2_ms == pytest.approx(list(ms))
    early = [e for c, e in zip(ms[1:], chain.errors[1:]) if c < 9.0]
    assert chain.early_to_last() == pytest.approx(sum(early) / len(early) / 0.40)


def test_at_the_same_size_the_upsampled_errors_are_the_evaluated_ones():
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    val = open_dataset(TINY_DATA, "val", (64, 64), train_augment=False)
    got = upsampled_errors(net, val, val, "rmse")
    assert got == pytest.approx(evaluate(net, val)["rmse"].tolist(), rel=1e-9)


def test_a_smaller_pass_is_scored_against_the_deployment_sizes_ground_truth():
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    small = open_dataset(TINY_DATA, "val", (32, 32), train_augment=False)
    full = open_dataset(TINY_DATA, "val", (64, 64), train_augment=False)
    got = upsampled_errors(net, small, full, "rmse")
    assert len(got) == paper_candidate().num_paths and all(math.isfinite(e) and e > 0 for e in got)
    assert got != pytest.approx(evaluate(net, small)["rmse"].tolist())


def test_a_first_pass_may_train_at_its_own_size():
    first, sizes = resolve_first("paper, largest@32x32", None, CONTEXT)
    assert list(first) == ["paper", "largest_train32x32"]
    assert sizes == {"paper": tuple(CONTEXT.config.train_size), "largest_train32x32": (32, 32)}
    assert first["paper"].candidate == paper_candidate()
    with pytest.raises(SystemExit, match="not a size"):
        resolve_first("paper@32", None, CONTEXT)
