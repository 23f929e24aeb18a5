"""Where bench_fidelity --per-exit says the ranking is lost (experiments/lib/per_exit.py): an estimate wrong at
one kind of path alone ranks exactly once that path is replaced, and the per-path figures find that path."""

from __future__ import annotations


import numpy as np

from experiments.lib import per_exit as _per_exit
from experiments.lib import predictor as _predictor

from explorer.space import SearchSpace


def _scrambled_at_last_exit(count=16, seed=4):
    """Labels, and an estimate equal to them but for the last decoder exit, whose errors are shuffled
    between the candidates (and read 0.1 too high)."""
    rng = np.random.default_rng(seed)
    cands = SearchSpace.from_yaml("anytime_depth").random_candidates(count, seed=5)
    labels = {c: [0.5] + sorted(rng.uniform(0.2, 0.45, c.num_paths - 1), reverse=True) for c in cands}
    shuffled = rng.permutation([labels[c][-1] for c in cands])
    estimated = {c: labels[c][:-1] + [float(x) + 0.1] for c, x in zip(cands, shuffled)}
    return cands, estimated, labels


def test_the_path_an_estimate_gets_wrong_is_the_one_whose_replacement_ranks_exactly():
    cands, estimated, labels = _scrambled_at_last_exit()
    last = _predictor.path_kinds(cands[0])[-1]
    assert all(_predictor.path_kinds(c)[-1] == last for c in cands)   # every candidate ends at the same exit
    taus = _per_exit.exact_at_taus(estimated, labels)
    assert taus[last] > 1 - 1e-9
    assert taus["none"] < 0.9
    assert all(t < 0.99 for k, t in taus.items() if k != last)


def test_per_path_figures_single_out_the_misordered_path():
    cands, estimated, labels = _scrambled_at_last_exit()
    last = _predictor.path_kinds(cands[0])[-1]
    figures = _per_exit.path_taus(estimated, labels)
    tau, overestimate, count = figures[last]
    assert count == len(cands) and abs(overestimate - 0.1) < 1e-9 and tau < 0.9
    assert all(t > 1 - 1e-9 and abs(gap) < 1e-12 for k, (t, gap, _) in figures.items() if k != last)


def test_last_exit_figures_follow_the_head_kind_whose_order_is_wrong():
    cands, _, labels = _scrambled_at_last_exit(count=24)
    estimated = {}
    plain = [c for c in cands if not c.exit_residual]
    reversed_last = sorted((labels[c][-1] for c in plain), reverse=True)
    order = sorted(plain, key=lambda c: labels[c][-1])
    for c in cands:   # residual heads exact, plain heads in reverse order
        estimated[c] = list(labels[c])
    for c, value in zip(order, reversed_last):
        estimated[c] = labels[c][:-1] + [value]
    taus = _per_exit.last_exit_taus(estimated, labels)
    assert taus["residual"] > 1 - 1e-9 and taus["plain"] < -1 + 1e-9
