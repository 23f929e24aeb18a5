"""Exits that correct the interpolated scan (``exits.residual: true``) against the paper's heads, which
predict depth: trains the paper design (and a candidate, if one is named) both ways, stand-alone, and
compares their anytime losses (tx2, U(0, 33 ms)) with the paper design with its own heads (the
baseline every study reports); a ratio below 1 favours residual exits.

    python benchmarks/bench_residual_exits.py [--candidate FILE.yaml | --study S --reports R]
        [--steps 600] [--reps 3]

With --study the candidate is the study's winner. Each repetition is one training seed; within it
every variant is trained, in an order that rotates. Trainings are cached (benchmarks/_labels.py).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import add_candidate_options, candidates_of, recipe, score, standalone, with_seed  # noqa: E402
from harness import Bench, interleave  # noqa: E402

KINDS = {False: "plain", True: "residual"}

if __name__ == "__main__":
    bench = Bench(__file__, "Residual exits (correcting the scan) against plain exit heads", __doc__)
    ap = bench.parser()
    add_candidate_options(ap)
    args = bench.parse_args(ap)
    cands = candidates_of(args)
    base = recipe(args.steps)
    variants = {(name, kind): dataclasses.replace(cand, exit_residual=residual)
                for name, cand in cands.items() for residual, kind in KINDS.items()}
    for (name, kind), variant in variants.items():
        bench.figure(f"{name}_{kind}_loss", f"{name} ({variant.key}), {kind} exits: anytime loss", "", "lower")
        bench.figure(f"{name}_{kind}_last_rmse", f"{name}, {kind} exits: last path RMSE", "m", "lower")
        bench.figure(f"{name}_{kind}_over_paper", f"{name}, {kind} exits / paper design with plain exits", "x",
                     "lower")
    for rep in bench.repetitions():
        got = interleave({key: (lambda v=v: standalone(v, with_seed(base, rep))) for key, v in variants.items()}, rep)
        paper = score(got["paper", "plain"])
        for (name, kind), entry in got.items():
            bench.add(f"{name}_{kind}_loss", score(entry))
            bench.add(f"{name}_{kind}_last_rmse", entry["rmse"][-1])
            bench.add(f"{name}_{kind}_over_paper", score(entry) / paper)
    bench.note(f"{args.steps} steps a training; each repetition is one seed")
    bench.finish()
