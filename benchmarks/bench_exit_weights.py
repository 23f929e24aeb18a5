"""Does weighting each exit's training loss by its share of the anytime loss (the probability that it
is the output when inference halts, on the study's device and budget) train better anytime networks
than equal weights? Trains the paper design (and a candidate, if one is named) both ways and compares
their anytime losses (tx2, U(0, 33 ms)); a ratio below 1 favours the anytime weights.

    python benchmarks/bench_exit_weights.py [--candidate FILE.yaml | --study S --reports R]
        [--steps 600] [--reps 3]

Each repetition is one training seed; within it every candidate is trained with both weightings, in
an order that rotates. Trainings are cached (benchmarks/_labels.py): a rerun only reads them.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import BUDGET, add_candidate_options, candidates_of, recipe, score, standalone, with_seed  # noqa: E402
from harness import Bench, interleave  # noqa: E402

from explorer.anytime import exit_loss_weights  # noqa: E402
from explorer.cost import candidate_cost, get_device  # noqa: E402

if __name__ == "__main__":
    bench = Bench(__file__, "Anytime-weighted exit losses against equal weights", __doc__)
    ap = bench.parser()
    add_candidate_options(ap)
    args = bench.parse_args(ap)
    cands = candidates_of(args)
    base = recipe(args.steps)
    runs = {}
    for name, cand in cands.items():
        weights = {"equal": None,
                   "anytime": exit_loss_weights(candidate_cost(cand).path_costs(get_device("tx2"), "time"), BUDGET)}
        for weighting, w in weights.items():
            runs[name, weighting] = (cand, w)
            bench.figure(f"{name}_{weighting}_loss", f"{name} ({cand.key}), {weighting} weights: anytime loss", "",
                         "lower")
        bench.figure(f"{name}_anytime_over_equal", f"{name}: anytime / equal weights", "x", "lower")
    others = [n for n in cands if n != "paper"]
    for other in others:
        bench.figure(f"{other}_over_paper_anytime", f"{other} (anytime weights) / paper design (equal weights)", "x",
                     "lower")
    for rep in bench.repetitions():
        def train_one(cand, w, seed=rep):
            return score(standalone(cand, dataclasses.replace(with_seed(base, seed), exit_weights=w)))
        loss = interleave({key: (lambda c=c, w=w: train_one(c, w)) for key, (c, w) in runs.items()}, rep)
        for (name, weighting), value in loss.items():
            bench.add(f"{name}_{weighting}_loss", value)
        for name in cands:
            bench.add(f"{name}_anytime_over_equal", loss[name, "anytime"] / loss[name, "equal"])
        for other in others:
            bench.add(f"{other}_over_paper_anytime", loss[other, "anytime"] / loss["paper", "equal"])
    bench.note(f"{args.steps} steps a training; each repetition is one seed")
    bench.finish()
