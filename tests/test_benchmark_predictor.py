"""The accuracy predictor bench_fidelity --predictor measures (experiments/lib/predictor.py): its features
follow the candidate's paths, a correction the data hold is learned, and every estimate is held out."""

from __future__ import annotations


import numpy as np
from scipy.stats import kendalltau

from experiments.lib import predictor as _predictor

from explorer.space import SearchSpace

NO_CORRECTION = np.zeros(_predictor.FEATURE_COUNT)


def _candidates(count=12):
    return SearchSpace.from_yaml("anytime_depth").random_candidates(count, seed=3)


def _errors(cand, rng):
    return [0.5] + sorted(rng.uniform(0.25, 0.45, cand.num_paths - 1), reverse=True)


def test_one_feature_row_per_learned_path():
    rng = np.random.default_rng(0)
    for cand in _candidates():
        kinds = _predictor.path_kinds(cand)
        assert len(kinds) == cand.num_paths - 1
        assert _predictor.exit_features(cand, _errors(cand, rng)).shape == (len(kinds), len(NO_CORRECTION))


def test_a_correction_the_results_hold_is_learned():
    # retrained = estimated - 0.1 on every path: the fit recovers it and the corrected anytime loss is the
    # retrained one's
    rng = np.random.default_rng(1)
    cands = _candidates()
    estimated = {c: _errors(c, rng) for c in cands}
    retrained = {c: [e[0]] + [x - 0.1 for x in e[1:]] for c, e in estimated.items()}
    weights = _predictor.fit(cands[1:], estimated, retrained)
    target = _predictor.corrected(cands[0], retrained[cands[0]], NO_CORRECTION)
    assert abs(_predictor.corrected(cands[0], estimated[cands[0]], weights) - target) < 2e-3


def test_held_out_estimates_rank_labels_a_correction_explains():
    # the estimate is off by an amount its features explain (plain heads read 0.1 too high): the corrected
    # estimates rank the labels better than the raw ones, from fits that never saw the candidate ranked
    rng = np.random.default_rng(2)
    cands = _candidates(16)
    retrained = {c: _errors(c, rng) for c in cands}
    estimated = {c: [r[0]] + [x + (0.0 if c.exit_residual else 0.1) for x in r[1:]] for c, r in retrained.items()}
    labels = {c: _predictor.corrected(c, retrained[c], NO_CORRECTION) for c in cands}
    raw = [_predictor.corrected(c, estimated[c], NO_CORRECTION) for c in cands]
    raw_tau = kendalltau(raw, [labels[c] for c in cands]).statistic
    held = _predictor.held_out_taus(estimated, retrained, labels, train_count=len(cands) - 1)
    assert len(held) == 1 and held[0] > raw_tau + 0.1 and held[0] > 0.8
