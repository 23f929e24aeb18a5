"""What matching the sensor is worth: the paper design trained with the paper's ideal scan (the
centre row, every column, exact) and trained with a realistic LiDAR model (mount 5 cm above the
camera and tilted 2 degrees down, 0.5 degree resolution, 2% dropout, 2 cm range noise), each
evaluated on validation frames whose scans the realistic model makes, and on ideal ones.

    python -m experiments.scan_model [--steps 300] [--frames 96] [--reps 3]

On the synthetic scenes at 64x64 (the search's training size) with the proxy recipe. Each repetition
is one training seed; within it both variants train, in an order that rotates.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import paper_candidate
from explorer.training.train import PROXY, evaluate, train

from benchmarks.harness import Bench, Case, interleave, run_suite

SIZE = (64, 64)
REALISTIC = "synthetic,dropout=0.02,fov=180,height=0.05,noise=0.02,resolution=0.5,tilt=2"
DATA = {"ideal": "synthetic", "realistic": REALISTIC}
BUDGET = "time:uniform:33ms"


def trained(data: str, cfg):
    net = build_network(paper_candidate())
    train(net, open_dataset(data, "train", SIZE, seed=cfg.seed), open_dataset(data, "val", SIZE, train_augment=False),
          cfg, val_limit=16)
    return net


def bench_scan_model(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_scan_model", "Scan model: training on the ideal centre row against a realistic LiDAR model", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=PROXY.steps)
    ap.add_argument("--frames", type=int, default=96, help="validation frames each network is evaluated on")
    args = bench.parse_args(ap, argv)
    costs = candidate_cost(paper_candidate()).path_costs(get_device("tx2"), "time")
    vals = {name: open_dataset(spec, "val", SIZE, train_augment=False) for name, spec in DATA.items()}
    for tr in DATA:
        for ev in DATA:
            bench.figure(f"train_{tr}_eval_{ev}_loss", f"trained on {tr} scans, evaluated on {ev} scans: anytime "
                         f"loss (tx2, {BUDGET})", "m", "lower")
            bench.figure(f"train_{tr}_eval_{ev}_last_rmse", f"trained on {tr}, evaluated on {ev}: last path RMSE",
                         "m", "lower")
    bench.figure("realistic_gain", "anytime loss on realistic scans: trained on realistic / trained on ideal",
                 "x", "lower")
    for rep in bench.repetitions():
        cfg = dataclasses.replace(PROXY, steps=args.steps, input_size=SIZE, seed=rep)
        nets = interleave({name: (lambda spec=spec: trained(spec, cfg)) for name, spec in DATA.items()}, rep)
        losses = {}
        for tr, net in nets.items():
            for ev, val in vals.items():
                rmse = list(evaluate(net, val, limit=args.frames)["rmse"])
                losses[tr, ev] = anytime_loss(costs, rmse, BUDGET)
                bench.add(f"train_{tr}_eval_{ev}_loss", losses[tr, ev])
                bench.add(f"train_{tr}_eval_{ev}_last_rmse", rmse[-1])
        bench.add("realistic_gain", losses["realistic", "realistic"] / losses["ideal", "realistic"])
    bench.note(f"paper design, {args.steps} proxy steps at {SIZE[0]}x{SIZE[1]}, {args.frames} validation frames; "
               f"realistic scans: {REALISTIC}")
    bench.finish()


CASES = (Case(bench_scan_model),)

if __name__ == "__main__":
    run_suite(CASES)
