"""When a time limit leaves a supernet only K steps: is it better stopped at step K of the usual
recipe (what a search does when its deadline comes first: the learning rate still high and, before
half the steps, the narrow widths never trained by progressive shrinking) or trained with a recipe of
K steps that it completes (the same schedule, compressed)?

Each repetition is one supernet seed: the search's recipe with ``--recipe-steps`` (default 300, the
planner's minimum) stopped after ``--steps`` K (default 140, about what a 5-minute search fit on a
2-core CPU), against the same recipe with K steps, trained to its end; the two are trained one after
the other, their order turning from seed to seed. Each one's estimates of the stand-alone label set
(bench_fidelity's random default-space candidates and the baselines) are ranked against the long
labels (the finalists' recipe 4x longer, mean of 2 seeds): Kendall tau, Spearman, top-5 recall.

    ANYTIME_BENCH_CACHE=benchmarks/labels python benchmarks/bench_short_supernet.py [--reps 3] [--steps 140]

The labels must be in the cache (``benchmarks/labels`` holds them): nothing is trained for them here.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _fidelity import estimate, fidelity_candidates, labels_of, rank_figures, supernet_evaluator  # noqa: E402
from harness import Bench, rotated  # noqa: E402

from explorer.space import SearchSpace  # noqa: E402
from explorer.study.config import SearchConfig  # noqa: E402
from explorer.supernet import train_supernet  # noqa: E402

VARIANTS = ("stopped", "complete")
FIGURES = {"tau": ("Kendall tau", "higher"), "spearman": ("Spearman", "higher"),
           "recall": ("top-5 recall in the best 10", "higher")}


def train_variant(name: str, seed: int, args, space: SearchSpace, config: SearchConfig, folder: Path) -> Path:
    """The supernet of ``name`` for ``seed``: stopped after ``args.steps`` of ``args.recipe_steps``, or a
    recipe of ``args.steps`` trained to its end."""
    steps = args.recipe_steps if name == "stopped" else args.steps
    recipe = dataclasses.replace(config.supernet_recipe(), steps=steps, seed=seed)
    out = folder / f"{name}-{seed}.pt"
    t0 = time.perf_counter()
    train_supernet(space, config.data, recipe, out, torch.device("cpu"), stop_after_steps=args.steps)
    print(f"  {name} (seed {seed}): {args.steps} steps of a {steps}-step recipe in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    return out


def main() -> None:
    bench = Bench(__file__, "a supernet stopped short of its recipe against a recipe as short, completed", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=140, help="the steps each supernet trains (default 140)")
    ap.add_argument("--recipe-steps", type=int, default=300, help="the stopped supernet's recipe (default 300)")
    ap.add_argument("--candidates", type=int, default=24, help="random candidates of the label set (default 24)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = bench.parse_args(ap)
    torch.set_num_threads(args.threads)
    space, config = SearchSpace.from_yaml("anytime_depth"), SearchConfig(study="short-supernet")
    candidates = [c for c in fidelity_candidates(space, args.candidates) if space.contains(c)]
    labels = {c: labels_of(c, "long") for c in candidates}
    candidates = [c for c in candidates if labels[c]]
    if len(candidates) < 10:
        raise SystemExit(f"{len(candidates)} candidates have long labels in the cache: point ANYTIME_BENCH_CACHE "
                         "at benchmarks/labels")
    long = [statistics.mean(labels[c]) for c in candidates]
    for name in VARIANTS:
        for key, (label, better) in FIGURES.items():
            bench.figure(f"{key}_{name}", f"{name}: {label} against the long labels", "", better)
    bench.figure("tau_gain", "complete minus stopped, Kendall tau in the same seed", "", "higher")
    with tempfile.TemporaryDirectory(prefix="bench-short-supernet-") as tmp:
        for seed in bench.repetitions():
            taus = {}
            for name in rotated(list(VARIANTS), seed):
                file = train_variant(name, seed, args, space, config, Path(tmp))
                evaluator = supernet_evaluator(file, space, config, require_complete=False)   # as a search reads it
                figures = rank_figures([estimate(evaluator, c) for c in candidates], long)
                del evaluator
                for key, value in figures.items():
                    bench.add(f"{key}_{name}", value)
                taus[name] = figures["tau"]
            bench.add("tau_gain", taus["complete"] - taus["stopped"])
    bench.note(f"cpu, torch threads {args.threads}; {args.steps} supernet steps; the stopped one's recipe "
               f"{args.recipe_steps} steps; {len(candidates)} candidates with long labels")
    bench.finish()


if __name__ == "__main__":
    main()
