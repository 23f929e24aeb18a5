"""Exits that correct the interpolated scan (`exits.residual: true`) against the paper's heads, which
predict depth: trains the paper design and a candidate both ways, stand-alone, interleaved, S seeds,
and prints every anytime loss (tx2, U(0, 33 ms)), each path's RMSE, and the ratios to the paper
design with its own heads (the baseline every study reports).

    .venv/bin/python benchmarks/bench_residual_exits.py [--candidate FILE.yaml | --study S --reports R]
        [--steps 600] [--seeds 3]

With --study the candidate is the study's winner (either way it is trained both ways).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import add_candidate_options, candidates_of, recipe, score, standalone, with_seed  # noqa: E402


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_candidate_options(ap, seeds=3)
    args = ap.parse_args()
    cands = candidates_of(args)
    base = recipe(args.steps)
    loss: dict[tuple[str, bool], list[float]] = {}
    for seed in range(args.seeds):
        for name, cand in cands.items():
            for residual in (False, True):
                variant = dataclasses.replace(cand, exit_residual=residual)
                t0 = time.perf_counter()
                entry = standalone(variant, with_seed(base, seed))
                loss.setdefault((name, residual), []).append(score(entry))
                print(f"seed {seed} {name} ({variant.key}) {'residual' if residual else 'plain'} exits: anytime loss "
                      f"{loss[name, residual][-1]:.4f}, rmse per path {' '.join(f'{x:.3f}' for x in entry['rmse'])} "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
    paper = loss["paper design", False]
    print(f"\n{args.steps} steps, {args.seeds} seeds; medians over seeds, every seed in brackets")
    for (name, residual), values in loss.items():
        ratios = [v / p for v, p in zip(values, paper)]
        print(f"  {name:12s} {'residual' if residual else 'plain':8s}: anytime loss {statistics.median(values):.4f} "
              f"({' / '.join(f'{v:.4f}' for v in values)}), ratio to the paper design (plain) "
              f"{statistics.median(ratios):.3f} ({' / '.join(f'{r:.3f}' for r in ratios)}); "
              f"mean-loss ratio {statistics.mean(values) / statistics.mean(paper):.3f}")
