"""The bound bench_search_value records beside its ratios (experiments/lib/comparison.py): no
anytime network made of the paths it measured does better."""

from __future__ import annotations


import numpy as np

from experiments.lib.comparison import floor_steps

from explorer.anytime import anytime_loss

BUDGET = "time:uniform:33ms"


def _networks(rng, count=6):
    """Networks as measured: (each path's cost, its error), the scan (path 0) the same for all."""
    trained = {}
    for n in range(count):
        paths = int(rng.integers(2, 5))
        costs = np.cumsum(rng.uniform(0.5, 12.0, paths))
        errors = np.sort(rng.uniform(0.2, 0.6, paths))[::-1]
        trained[f"net{n}"] = ([0.1, *costs.tolist()], [0.9, *errors.tolist()])
    return trained


def test_the_bound_is_the_best_path_at_the_cheapest_cost():
    trained = {"slow": ([0.1, 9.0, 20.0], [0.9, 0.4, 0.25]), "fast": ([0.1, 2.0], [0.9, 0.5])}
    assert floor_steps(trained) == ([0.0, 2.0], [0.9, 0.25])


def test_no_network_measured_beats_the_bound():
    rng = np.random.default_rng(4)
    for _ in range(20):
        trained = _networks(rng)
        bound = anytime_loss(*floor_steps(trained), BUDGET)
        assert all(anytime_loss(*measured, BUDGET) >= bound for measured in trained.values())
        assert bound < anytime_loss([0.0], [0.9], BUDGET)   # any path at all beats the scan alone
