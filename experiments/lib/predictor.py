"""An accuracy predictor over the supernet's estimate, measured by bench_fidelity --predictor.

The supernet's per-exit errors, corrected by a ridge regression over each exit's description (which
exit, the head kind, the LiDAR branch, the widths, the supernet's own error there) fitted on other
candidates' retrained errors, as a search could fit it on the finalists and baselines that earlier
studies of the same space and data retrained. A per-exit correction carries over between devices and
budgets (the anytime loss weighs the exits by their costs afterwards). Each candidate's corrected
estimate comes from a fit that did not see it, so the rank figures are held out."""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import kendalltau

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.space import Candidate

from experiments.lib.labels import BUDGET

PATH_KINDS = ("lidar", "encoder3", "encoder5", "exit0", "exit1", "exit2", "exit3", "exit4")
#: the columns of exit_features: the path kinds, 7 descriptions, the supernet's error, a constant
FEATURE_COUNT = len(PATH_KINDS) + 9
RIDGE = 1.0     # the regression's penalty: with a handful of candidates the fit must stay small


def path_kinds(cand: Candidate) -> list[str]:
    """The learned paths of ``cand`` in the order of its metrics (path 0, the interpolated scan, left out)."""
    return (["lidar"] * cand.lidar_exit + [f"encoder{b}" for b in sorted(cand.encoder_exits)]
            + [f"exit{e}" for e in sorted(cand.exits)])


def exit_features(cand: Candidate, estimated: list[float]) -> np.ndarray:
    """One row per learned path: which path it is, the candidate's head kind, LiDAR branch and widths, the
    decoder width the exit reads, and the supernet's error there; a constant last."""
    rows = []
    for kind, err in zip(path_kinds(cand), estimated[1:]):
        stage = int(kind[-1]) if kind.startswith("exit") else 0
        width = math.log2(cand.decoder_widths[stage - 1]) / 8 if stage else 0.0
        rows.append([kind == k for k in PATH_KINDS] + [
            cand.head_depth == 2, cand.exit_residual, cand.ecu, cand.width_mult, cand.encoder_blocks / 9,
            width, cand.lidar_first, err, 1.0])
    return np.asarray(rows, dtype=float)


def fit(cands: list[Candidate], estimated: dict, retrained: dict) -> np.ndarray:
    """Ridge weights of (retrained - estimated) per learned path, over ``cands`` (the constant unpenalised)."""
    x = np.vstack([exit_features(c, estimated[c]) for c in cands])
    y = np.concatenate([np.subtract(retrained[c][1:], estimated[c][1:]) for c in cands])
    penalty = RIDGE * np.eye(x.shape[1])
    penalty[-1, -1] = 0.0
    return np.linalg.solve(x.T @ x + penalty, x.T @ y)


def corrected(cand: Candidate, estimated: list[float], weights: np.ndarray) -> float:
    """The anytime loss (tx2, BUDGET) of ``cand`` with its supernet errors corrected by ``weights``."""
    errors = [estimated[0]] + list(np.asarray(estimated[1:]) + exit_features(cand, estimated) @ weights)
    costs = candidate_cost(cand).path_costs(get_device("tx2"), "time")
    return anytime_loss(costs, errors, BUDGET)


def held_out_taus(estimated: dict, retrained: dict, labels: dict, train_count: int, draws: int = 20,
                  seed: int = 0) -> list[float]:
    """Kendall tau against ``labels`` of the corrected estimates, each candidate's from a fit on
    ``train_count`` others drawn at random (all the others: one draw); one tau per draw."""
    cands = [c for c in labels if c in estimated and c in retrained]
    rng = np.random.default_rng(seed)
    train_count = min(train_count, len(cands) - 1)
    taus = []
    for _ in range(1 if train_count == len(cands) - 1 else draws):
        values = []
        for c in cands:
            others = [o for o in cands if o is not c]
            chosen = [others[i] for i in rng.choice(len(others), train_count, replace=False)]
            values.append(corrected(c, estimated[c], fit(chosen, estimated, retrained)))
        taus.append(float(kendalltau(values, [labels[c] for c in cands]).statistic))
    return taus
