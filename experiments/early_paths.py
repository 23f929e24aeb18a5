"""Do the early-path levers pay? The paper design retrained from scratch with the finalists' recipe of a
default study (``make search``'s settings: the synthetic scenes, N steps at 64x64 then the tuning
steps at 224x224, where every path is measured on validation frames), plain and with each lever,
costed on the TX2 for its 33 ms uniform budget.

Levers: self-distillation of weight W (``--distill``, ``explorer train --self-distill W``), and the
runtime's rule that a halt returns the most accurate path ready (never a path less accurate than one
already returned): every anytime loss here counts it; ``<name>_eq1_N`` is the same network's loss as
the paper's Eq. 1 counts it (the last path ready, whatever its error), so the two side by side say
what the rule is worth. Figures per network: anytime loss, its ratio to the plain design's (for the 33 ms
budget and for a short one, ``SHORT_BUDGET``), and its early-to-last ratio (the mean error of its paths ready
before 9 ms on the TX2 over its last path's).

    python -m experiments.early_paths --only bench_early_paths [--steps 300] [--distill 0.5,1] [--reps 3]
    python -m experiments.early_paths --only bench_heads [--steps 300] [--reps 3]

``bench_heads`` asks the same of a head sized for its position: the paper design's first exit with a
two-layer head.

Every network is scored as it ships (an exit no more accurate than an earlier path left out).

Each repetition is one training seed; the networks train in an order that rotates.
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from explorer.anytime import anytime_loss, interval_probabilities
from explorer.study.config import SearchConfig
from explorer.training.train import evaluated_frames
from explorer.data import open_dataset

from benchmarks.harness import Bench, Case, rotated, run_suite
from experiments.lib.retraining import EARLY_MS, early_to_last, held_out_data, resolve_networks, retrained


#: a budget that ends soon after the paper design's last path is ready on the TX2, so that its early paths serve
#: most halts: what a lever for the early paths is worth where they count
SHORT_BUDGET = "time:uniform:15ms"


def declare(bench: Bench, names: list[str], steps: int) -> None:
    for name in names:
        bench.figure(f"{name}_anytime_{steps}", f"{name}: anytime loss (tx2, 33 ms uniform), {steps} steps", "m",
                     "lower")
        bench.figure(f"{name}_anytime_short_{steps}", f"{name}: anytime loss (tx2, {SHORT_BUDGET}), {steps} steps",
                     "m", "lower")
        bench.figure(f"{name}_eq1_{steps}", f"{name}: anytime loss counting the last path ready (Eq. 1), "
                     f"{steps} steps", "m", "lower")
        bench.figure(f"{name}_early_to_last_{steps}", f"{name}: mean RMSE of its paths ready before {EARLY_MS:g} ms "
                     f"on tx2 over its last path's, {steps} steps", "x", "lower")
        if name != "paper":
            bench.figure(f"ratio_{name}_{steps}", f"{name} / paper, anytime loss, {steps} steps", "", "lower")
            bench.figure(f"ratio_short_{name}_{steps}", f"{name} / paper, anytime loss ({SHORT_BUDGET}), {steps} steps",
                         "", "lower")


def compare(bench: Bench, specs: str, steps: int, first_seed: int, study: str) -> None:
    """Retrains the paper design and the networks ``specs`` names (``experiments.lib.retraining``) with the
    finalists' recipe of a default study at ``steps`` steps, one seed per repetition, and adds each one's
    figures (:func:`declare`) to ``bench``."""
    context = SearchConfig(study=study, finalist_steps=steps).resolve()
    config = context.config
    networks = resolve_networks(specs, None, context)
    declare(bench, list(networks), steps)
    val_from = evaluated_frames(open_dataset(config.data, "val", config.input_size, train_augment=False),
                                config.val_limit)
    recipe = config.finalist_recipe()
    bench.note(f"{', '.join(networks)}: {steps} steps at {config.train_size[0]}x{config.train_size[1]} then "
               f"{config.tuning_steps} at {config.input_size[0]}x{config.input_size[1]}, measured there on the "
               f"validation frames from {val_from} of {config.data}; tx2, {config.budgets[0]}; seeds "
               f"{first_seed} on")
    for rep in bench.repetitions():
        seed = first_seed + rep
        data = held_out_data(context, seed, val_from)
        loss, short = {}, {}
        for name in rotated(list(networks), rep):
            t0 = time.perf_counter()
            got = retrained(networks[name], recipe, seed, data, context)
            loss[name] = anytime_loss(got.costs, got.errors, context.budgets[0])
            eq1 = float(np.dot(got.errors, interval_probabilities(got.costs, context.budgets[0])))
            bench.add(f"{name}_anytime_{steps}", loss[name])
            short[name] = anytime_loss(got.costs, got.errors, SHORT_BUDGET)
            bench.add(f"{name}_anytime_short_{steps}", short[name])
            bench.add(f"{name}_eq1_{steps}", eq1)
            bench.add(f"{name}_early_to_last_{steps}", early_to_last(got.candidate, got.errors, config))
            print(f"  seed {seed}: {name} anytime {loss[name]:.4f} (Eq. 1: {eq1:.4f}), as shipped, by path "
                  f"{[round(e, 4) for e in got.errors]} ({time.perf_counter() - t0:.0f} s)"
                  + "".join(f"; {d.describe(config.metric)}" for d in got.dropped), flush=True)
        for name in networks:
            if name != "paper":
                bench.add(f"ratio_{name}_{steps}", loss[name] / loss["paper"])
                bench.add(f"ratio_short_{name}_{steps}", short[name] / short["paper"])
    bench.finish()


def bench_early_paths(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_early_paths", "Early paths: self-distillation and never-worse on the paper design",
                  __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=300, help="steps at the training size (default 300, the "
                    "finalists'); then the default study's tuning steps at 224x224")
    ap.add_argument("--distill", default="0.5,1", help="self-distillation weights to try, comma-separated")
    ap.add_argument("--first-seed", type=int, default=100, help="the first repetition's seed (default 100)")
    args = bench.parse_args(ap, argv)
    weights = [w.strip() for w in args.distill.split(",") if w.strip()]
    compare(bench, ",".join(["paper"] + [f"paper:distill={w}" for w in weights]), args.steps, args.first_seed,
            "early-paths")


#: the paper design with its first exit (after the ECU, at the encoder's stride) given a two-layer head, narrow
#: and wide, the other exits' heads as they are
HEAD_NETWORKS = "paper,paper:ecu_head_depth=2:ecu_head_width=32,paper:ecu_head_depth=2:ecu_head_width=64"


def bench_heads(argv: Sequence[str] | None = None) -> None:
    """Do exit heads sized for their position pay? The paper design, and the same with a two-layer head
    (32 or 64 channels wide) on its first exit only, retrained as above."""
    bench = Bench("bench_heads", "Early paths: a larger head on the first exit", bench_heads.__doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=300, help="steps at the training size (default 300, the "
                    "finalists'); then the default study's tuning steps at 224x224")
    ap.add_argument("--first-seed", type=int, default=100, help="the first repetition's seed (default 100)")
    args = bench.parse_args(ap, argv)
    compare(bench, HEAD_NETWORKS, args.steps, args.first_seed, "heads")


CASES = (Case(bench_early_paths), Case(bench_heads))

if __name__ == "__main__":
    run_suite(CASES)
