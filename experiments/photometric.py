"""Can a study without depth trust its score? On frames that have both exact depth and the camera's
motion, networks of the space are trained self-supervised (as on a recording without depth) and each
is scored twice: every path's RMSE and every path's photometric error
(explorer.training.selfsup.photometric_score, the score of a study on a recording without depth).
Figures: Kendall's tau between the two over every (network, path) pair past the scan
(``path_tau``: 1 means the photometric error orders depth maps as RMSE does), and between the
networks' anytime losses counted as the paper's Eq. 1 (``kendall_tau``; the search's own loss, which
never returns a path worse than the scan, ties every network that no path of improves on it).

    python -m experiments.photometric [--space tiny] [--candidates 6] [--steps 200] [--frames 48] [--reps 3]

On synthetic sequences at 64x64 (the search's training size), the camera's motion given by the
data: this measures the score, not the LiDAR's scan matching (tests/data/test_odometry.py checks
that). Each repetition draws its own candidates from the default space and trains them in an
order that rotates.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import torch
from scipy.stats import kendalltau

import numpy as np

from explorer.anytime import interval_probabilities
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import SearchSpace
from explorer.training.train import PROXY, evaluate, train

from benchmarks.harness import Bench, Case, interleave, run_suite

SIZE = (64, 64)
DATA = "synthetic-seq:600:60"
BUDGET = "time:uniform:33ms"


def scored(candidate, train_set, val_set, cfg, frames: int) -> tuple[list[float], list[float], np.ndarray]:
    """(RMSE per path, photometric error per path, each path's weight in Eq. 1 on the TX2) of
    ``candidate`` trained self-supervised."""
    torch.manual_seed(cfg.seed)
    net = build_network(candidate)
    train(net, train_set, val_set, cfg, val_limit=8)
    metrics = evaluate(net, val_set, limit=frames)
    costs = candidate_cost(candidate).path_costs(get_device("tx2"), "time")
    return list(metrics["rmse"]), list(metrics["photometric"]), interval_probabilities(costs, BUDGET)


def bench_photometric(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_photometric", "Photometric score: does it rank networks as RMSE does?", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=6, help="networks of the space per repetition")
    ap.add_argument("--steps", type=int, default=200, help="self-supervised training steps per network")
    ap.add_argument("--frames", type=int, default=48, help="validation frames each network is scored on")
    ap.add_argument("--data", default=DATA, help=f"sequences with depth and poses (default {DATA})")
    ap.add_argument("--space", default="tiny", help="the space the networks are drawn from (default tiny)")
    args = bench.parse_args(ap, argv)
    space = SearchSpace.from_yaml(args.space)
    train_set = open_dataset(args.data, "train", SIZE)
    val_set = open_dataset(args.data, "val", SIZE)
    bench.figure("path_tau", "Kendall tau between RMSE and photometric error over every network's paths", "",
                 "higher")
    bench.figure("kendall_tau", "Kendall tau between the networks' Eq. 1 anytime losses by RMSE and by "
                 "photometric error", "", "higher")
    bench.figure("best_by_photometric_rmse_ratio", "Eq. 1 anytime loss by RMSE of the network the photometric "
                 "score ranks first, over the best by RMSE", "x", "lower")
    for rep in bench.repetitions():
        cfg = dataclasses.replace(PROXY, steps=args.steps, input_size=SIZE, seed=rep, supervision="self",
                                  batch_size=8)
        candidates = space.random_candidates(args.candidates, seed=rep)
        runs = interleave({c.key: (lambda c=c: scored(c, train_set, val_set, cfg, args.frames)) for c in candidates}, rep)
        by_rmse = [float(np.dot(runs[c.key][0], runs[c.key][2])) for c in candidates]
        by_photo = [float(np.dot(runs[c.key][1], runs[c.key][2])) for c in candidates]
        paths_rmse = [e for c in candidates for e in runs[c.key][0][1:]]
        paths_photo = [e for c in candidates for e in runs[c.key][1][1:]]
        for c, r, ph in zip(candidates, by_rmse, by_photo):
            print(f"  rep {rep} {c.key}: Eq. 1 by RMSE {r:.4f}, by photometric {ph:.4f}; RMSE by path "
                  f"{[round(e, 4) for e in runs[c.key][0]]}, photometric {[round(e, 5) for e in runs[c.key][1]]}",
                  flush=True)
        bench.add("path_tau", float(kendalltau(paths_rmse, paths_photo).statistic))
        bench.add("kendall_tau", float(kendalltau(by_rmse, by_photo).statistic))
        pick = min(range(len(candidates)), key=lambda i: by_photo[i])
        bench.add("best_by_photometric_rmse_ratio", by_rmse[pick] / min(by_rmse))
    bench.note(f"{args.candidates} networks of {args.space} per repetition, {args.steps} self-supervised proxy steps "
               f"at {SIZE[0]}x{SIZE[1]} on {args.data}, {args.frames} validation frames, tx2 {BUDGET}")
    bench.finish()


CASES = (Case(bench_photometric),)

if __name__ == "__main__":
    run_suite(CASES)
