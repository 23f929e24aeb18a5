"""Can a study without depth trust its score? On frames that have both exact depth and the camera's
motion, networks of the space are trained self-supervised (as on a recording without depth) and each
is scored twice: its anytime loss with every path's RMSE, and with every path's photometric error
(explorer.training.selfsup.photometric_score, the score of a study on a recording without depth).
The figure is Kendall's tau between the two rankings: 1 means the photometric score picks the
networks RMSE would pick.

    python -m experiments.photometric [--candidates 6] [--steps 200] [--frames 48] [--reps 3]

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

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import SearchSpace
from explorer.training.train import PROXY, evaluate, train

from benchmarks.harness import Bench, Case, interleave, run_suite

SIZE = (64, 64)
DATA = "synthetic-seq:600:60"
BUDGET = "time:uniform:33ms"


def scored(candidate, train_set, val_set, cfg, frames: int) -> tuple[float, float]:
    """(anytime loss by RMSE, by photometric error) of ``candidate`` trained self-supervised."""
    torch.manual_seed(cfg.seed)
    net = build_network(candidate)
    train(net, train_set, val_set, cfg, val_limit=8)
    metrics = evaluate(net, val_set, limit=frames)
    costs = candidate_cost(candidate).path_costs(get_device("tx2"), "time")
    return (anytime_loss(costs, list(metrics["rmse"]), BUDGET),
            anytime_loss(costs, list(metrics["photometric"]), BUDGET))


def bench_photometric(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_photometric", "Photometric score: does it rank networks as RMSE does?", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=6, help="networks of the space per repetition")
    ap.add_argument("--steps", type=int, default=200, help="self-supervised training steps per network")
    ap.add_argument("--frames", type=int, default=48, help="validation frames each network is scored on")
    ap.add_argument("--data", default=DATA, help=f"sequences with depth and poses (default {DATA})")
    args = bench.parse_args(ap, argv)
    space = SearchSpace.from_yaml("anytime_depth")
    train_set = open_dataset(args.data, "train", SIZE)
    val_set = open_dataset(args.data, "val", SIZE)
    bench.figure("kendall_tau", "Kendall tau between the networks' anytime losses by RMSE and by photometric "
                 "error", "", "higher")
    bench.figure("best_by_photometric_rmse_ratio", "anytime loss by RMSE of the network the photometric score "
                 "ranks first, over the best by RMSE", "x", "lower")
    for rep in bench.repetitions():
        cfg = dataclasses.replace(PROXY, steps=args.steps, input_size=SIZE, seed=rep, supervision="self",
                                  batch_size=8)
        candidates = space.random_candidates(args.candidates, seed=rep)
        runs = interleave({c.key: (lambda c=c: scored(c, train_set, val_set, cfg, args.frames)) for c in candidates}, rep)
        by_rmse = [runs[c.key][0] for c in candidates]
        by_photo = [runs[c.key][1] for c in candidates]
        for c in candidates:
            print(f"  rep {rep} {c.key}: anytime loss by RMSE {runs[c.key][0]:.4f}, by photometric {runs[c.key][1]:.4f}")
        bench.add("kendall_tau", float(kendalltau(by_rmse, by_photo).statistic))
        pick = min(range(len(candidates)), key=lambda i: by_photo[i])
        bench.add("best_by_photometric_rmse_ratio", by_rmse[pick] / min(by_rmse))
    bench.note(f"{args.candidates} networks of anytime_depth per repetition, {args.steps} self-supervised proxy steps "
               f"at {SIZE[0]}x{SIZE[1]} on {args.data}, {args.frames} validation frames, tx2 {BUDGET}")
    bench.finish()


CASES = (Case(bench_photometric),)

if __name__ == "__main__":
    run_suite(CASES)
