"""Does weighting each exit's training loss by its share of the anytime loss (the probability that it
is the output when inference halts, on the study's device and budget) train better anytime networks
than equal weights? Trains a candidate and the paper design both ways, interleaved, S seeds, and
prints every anytime loss (tx2, U(0, 33 ms)) and the ratios.

    .venv/bin/python benchmarks/bench_exit_weights.py [--candidate FILE.yaml | --study S --reports R]
        [--steps 600] [--seeds 2]

Without --candidate or --study only the paper design is trained.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import BUDGET, add_candidate_options, candidates_of, recipe, score, standalone, with_seed  # noqa: E402

from explorer.cost import get_device  # noqa: E402
from explorer.anytime import exit_loss_weights  # noqa: E402
from explorer.cost import candidate_cost  # noqa: E402

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_candidate_options(ap, seeds=2)
    args = ap.parse_args()
    cands = candidates_of(args)
    base = recipe(args.steps)
    loss: dict[tuple[str, str], list[float]] = {}
    for seed in range(args.seeds):
        for name, cand in cands.items():
            weights = {"equal": None, "anytime": exit_loss_weights(candidate_cost(cand).path_costs(get_device("tx2"), "time"), BUDGET)}
            for weighting, w in weights.items():
                import dataclasses
                cfg = dataclasses.replace(with_seed(base, seed), exit_weights=w)
                t0 = time.perf_counter()
                entry = standalone(cand, cfg)
                loss.setdefault((name, weighting), []).append(score(entry))
                print(f"seed {seed} {name} ({cand.key}) {weighting} weights "
                      f"{'-' if w is None else '/'.join(f'{x:.2f}' for x in w)}: anytime loss {loss[name, weighting][-1]:.4f}, "
                      f"rmse per path {' '.join(f'{x:.3f}' for x in entry['rmse'])} ({time.perf_counter() - t0:.0f} s)",
                      flush=True)
    for name in cands:
        e, a = loss[name, "equal"], loss[name, "anytime"]
        print(f"{name}: equal {' / '.join(f'{x:.4f}' for x in e)} (mean {statistics.mean(e):.4f}), anytime "
              f"{' / '.join(f'{x:.4f}' for x in a)} (mean {statistics.mean(a):.4f}): "
              f"{statistics.mean(a) / statistics.mean(e):.3f}x")
    if len(cands) == 2:
        other = [n for n in cands if n != "paper design"][0]
        for weighting in ("equal", "anytime"):
            ratio = statistics.mean(loss[other, weighting]) / statistics.mean(loss["paper design", weighting])
            print(f"{other} / paper design, both trained with {weighting} weights: {ratio:.3f}")
        ratio = statistics.mean(loss[other, "anytime"]) / statistics.mean(loss["paper design", "equal"])
        print(f"{other} (anytime weights) / paper design (equal weights): {ratio:.3f}")
