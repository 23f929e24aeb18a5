"""A finished study's winner against the paper design in held-out retraining, at several recipe
lengths: does the winner's lead hold on frames the study never chose with, and does it grow when both
networks are trained longer than a search on this machine can afford?

Each repetition is one training seed (``--first-seed`` on, none of them the study's). In it the
study's winner and the paper design are retrained from scratch with the study's finalists' recipe at
each of ``--steps`` (``N`` steps at the training size, then the tuning steps the study's settings give
N at the deployment size; ``N+T`` for T tuning steps instead), the recipes and the two networks in an
order that rotates from seed to seed, and every path is measured at the deployment size on the
validation frames the study did not use (``--val-from`` on: by default those after the ones the
study measured its finalists on, its ``val_limit``), then costed on the study's device for its
budget. Figures per recipe (suffix ``N``, or ``N_tuneT``): the winner's anytime loss over the paper
design's (``ratio_N``, below 1 the winner is better), every network's anytime loss and last path's
error, and a bound (``floor_ratio_N``): the anytime loss, over the paper design's, of a network
whose every path past the scan were as accurate as the best path of any network measured and ready
when their cheapest path is. A network of the space does better only with a path more accurate than
any measured here: a target below the bound asks for more accurate networks (a longer recipe, a
richer space), not a better choice among these.

``--networks`` names what is retrained (default ``winner,paper``): ``winner`` (the study's),
``paper`` (the paper design), ``largest`` (the largest network of the study's space, every exit it
allows), or a candidate YAML (as the report gives each network, or ``explorer train`` takes), named
after its file; ``:FIELD=VALUE`` after one changes a field of it, to ask what a network just outside
the space would do (``winner:encoder_blocks=11``: the winner with two more encoder blocks), and
``:weights=anytime`` trains it with each exit's loss weighted by its share of the study's anytime loss
(``explorer train --exit-weights anytime``) instead of equal weights, and ``:distill=W`` trains it with
self-distillation of weight W (``explorer train --self-distill W``). Each network also gets its
early error (``<name>_early_N``): the mean error of its paths ready before 9 ms on the TX2, and its
early-to-last ratio (``<name>_early_to_last_N``): that over its last path's. A network beside the winner and
the paper design adds ``ratio_<name>_N``, its anytime loss over the paper design's trained with the
same weights when that is measured too (``paper:weights=anytime``), else the plain one's (``<name>``:
the spec, punctuation as underscores).

    python -m experiments.held_out --study tx2-anytime_depth [--steps 300,2000+130] [--reps 3]
        [--networks winner,paper,winner:encoder_blocks=11,winner:weights=anytime,paper:weights=anytime]

``--only early_path_levers`` (``bench_early_path_levers``) runs the same with the early-path levers by
default: heads sized for their position alone, on the winner and the paper design, and with
self-distillation on the winner; ``--only self_distillation`` with self-distillation (weight 1) on
both; ``--only first_paths`` with the winner without its LiDAR-only exit.

Run it after ``make search`` (whose study it reads, from ``reports/``, untouched).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Sequence


from explorer.anytime import anytime_loss
from explorer.data import open_dataset
from explorer.study.config import SearchConfig
from explorer.study.results import winner
from explorer.training.train import evaluated_frames

from benchmarks.harness import Bench, Case, rotated, run_suite
from experiments.lib.comparison import floor_steps
from experiments.lib.retraining import (EARLY_MS, Network, add_study_options, early_error, early_to_last, held_out_data,
                                        open_study, reference_of, resolve_networks, retrained)


def parse_recipes(text: str, config: SearchConfig) -> dict[str, tuple[int, int]]:
    """``--steps``: "300,2000+130" -> {"300": (300, the study's tuning for 300 steps), "2000_tune130":
    (2000, 130)}."""
    recipes = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        steps, plus, tune = item.partition("+")
        try:
            n = int(steps)
            t = int(tune) if plus else dataclasses.replace(config, finalist_steps=max(n, 1)).tuning_steps
        except ValueError:
            raise SystemExit(f"--steps: {item!r} is not N or N+T (whole numbers of steps)") from None
        if n < 1 or t < 0:
            raise SystemExit(f"--steps: {item!r} needs N >= 1 and T >= 0")
        recipes[f"{n}_tune{t}" if plus else str(n)] = (n, t)
    if not recipes:
        raise SystemExit("--steps: give at least one recipe length")
    return recipes


def declare(bench: Bench, recipes: dict[str, tuple[int, int]], networks: dict[str, Network], metric: str,
            unit: str) -> None:
    for suffix, (n, tune) in recipes.items():
        recipe = f"{n} steps + {tune} at the deployment size"
        for name in networks:
            if name == "winner":
                bench.figure(f"ratio_{suffix}", f"winner / {reference_of(name, networks)}, anytime loss, {recipe}", "",
                             better="lower")
            elif name != "paper":
                bench.figure(f"ratio_{name}_{suffix}", f"{name} ({networks[name].candidate.key}) / "
                             f"{reference_of(name, networks)}, anytime loss, {recipe}", "", better="lower")
        bench.figure(f"floor_ratio_{suffix}", f"bound: the most accurate path of any network, as if ready when "
                     f"the cheapest is, / paper design, {recipe}", "", better="lower")
        for name in networks:
            bench.figure(f"{name}_anytime_{suffix}", f"{name}: anytime loss, {recipe}", unit, better="lower")
            bench.figure(f"{name}_last_{suffix}", f"{name}: last path's {metric}, {recipe}", unit, better="lower")
            bench.figure(f"{name}_early_{suffix}", f"{name}: mean {metric} of its paths ready before "
                         f"{EARLY_MS:g} ms on tx2, {recipe}", unit, better="lower")
            bench.figure(f"{name}_early_to_last_{suffix}", f"{name}: mean {metric} of its paths ready before "
                         f"{EARLY_MS:g} ms on tx2 over its last path's, {recipe}", "x", better="lower")


#: exit heads sized for their position: two pointwise layers, 64 channels wide, on the exits in the image
#: encoder and after the ECU (a network without such an exit keeps the heads it has)
EARLY_HEADS = "encoder_head_depth=2:encoder_head_width=64:ecu_head_depth=2:ecu_head_width=64"
#: the early-path levers: heads per position alone on the winner and the paper design, and with
#: self-distillation on the winner, the network a study ships (self-distillation alone: bench_held_out's
#: ``:distill=1``)
LEVER_NETWORKS = f"winner,paper,winner:{EARLY_HEADS},paper:{EARLY_HEADS},winner:{EARLY_HEADS}:distill=1"


def bench_held_out(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_held_out", "a study's winner against the paper design in held-out retraining, by recipe "
                  "length", __doc__)
    run_held_out(bench, argv, "winner,paper", "300,2000+130")


def bench_early_path_levers(argv: Sequence[str] | None = None) -> None:
    """Do the early-path levers pay on a study's winner, and after the long recipe? The held-out
    experiment (above) with heads sized for their position (two pointwise layers, 64 wide, on the encoder
    and ECU exits), on a study's winner and on the paper design, and on the winner with
    self-distillation of weight 1 as well, each beside the plain networks on the same seeds, after the
    finalists' recipe and the long one by default."""
    bench = Bench("bench_early_path_levers", "early-path levers on a study's winner and the paper design, by "
                  "recipe length", bench_early_path_levers.__doc__)
    run_held_out(bench, argv, LEVER_NETWORKS, "300,2000+130")


def bench_self_distillation(argv: Sequence[str] | None = None) -> None:
    """Does self-distillation (weight 1) pay on a study's winner and on the paper design after the long
    recipe? The held-out experiment (above) with both networks trained with it and without it, on the
    same seeds."""
    bench = Bench("bench_self_distillation", "self-distillation on a study's winner and the paper design, by "
                  "recipe length", bench_self_distillation.__doc__)
    run_held_out(bench, argv, "winner,paper,winner:distill=1,paper:distill=1", "300,2000+130")


def bench_first_paths(argv: Sequence[str] | None = None) -> None:
    """What does a study's winner owe its LiDAR-only exit, the exit that holds its early-to-last ratio up?
    The held-out experiment (above) with the winner as it is and without that exit (which sees one scan
    row), beside the paper design, on the same seeds."""
    bench = Bench("bench_first_paths", "a study's winner with and without its LiDAR-only exit, by recipe length",
                  bench_first_paths.__doc__)
    run_held_out(bench, argv, "winner,paper,winner:lidar_exit=false", "300,2000+130")


def run_held_out(bench: Bench, argv: Sequence[str] | None, networks: str, steps: str) -> None:
    """Retrains, per seed, every network at every recipe (the defaults of ``--networks`` and ``--steps``:
    ``networks`` and ``steps``) and records the figures ``declare`` names."""
    ap = bench.parser()
    ap.add_argument("--steps", default=steps, help="recipes, comma-separated: N steps at the training "
                    "size then the study's tuning steps, or N+T for T tuning steps (default %(default)s; "
                    "300 is the finalists' recipe, 2000+130 one about 7 times as long with the same share of "
                    "tuning)")
    ap.add_argument("--val-from", type=int, help="the first validation frame measured (default: the first after "
                    "those the study measured its finalists on)")
    ap.add_argument("--networks", default=networks, help="what to retrain, comma-separated: winner, paper, "
                    "largest (the largest network of the study's space) or candidate YAML files, each with "
                    ":FIELD=VALUE changes if any (winner:encoder_blocks=11), :weights=anytime to weight its exits' "
                    "training losses by their share of the anytime loss, :distill=W for self-distillation of "
                    "weight W; paper among them (default %(default)s)")
    add_study_options(ap)
    args = bench.parse_args(ap, argv)
    study, context = open_study(args)
    config = context.config
    networks = resolve_networks(args.networks, study, context)
    unit = "m" if config.metric in ("rmse", "mae") else ""
    recipes = parse_recipes(args.steps, config)
    declare(bench, recipes, networks, config.metric, unit)
    val = open_dataset(config.data, "val", config.input_size, train_augment=False)
    n_val = len(val)
    if args.val_from is None:
        args.val_from = evaluated_frames(val, config.val_limit)
    best = winner(study)
    chosen = (f"winner {networks['winner'].candidate.key} (trial {best.number}, anytime loss {best.values[0]:.4f} "
              f"in the study, the best of {config.finalists} finalists retrained {config.finalist_steps}+"
              f"{config.tuning_steps} steps)" if "winner" in networks else "")
    others = ", ".join(f"{name} {n.candidate.key}" for name, n in networks.items() if name not in ("winner", "paper"))
    bench.note(f"study {args.study}: {'; '.join(filter(None, (chosen, others)))}; {config.device}, "
               f"{config.budgets[0]}; "
               f"recipe: the finalists' at {config.train_size[0]}x{config.train_size[1]}, then the study's tuning "
               f"steps at {config.input_size[0]}x{config.input_size[1]} (N+T in --steps: T there); measured on "
               f"validation frames {args.val_from} to {n_val - 1} of {config.data}; seeds {args.first_seed} on; cpu, "
               f"torch threads {args.threads}")

    for rep in bench.repetitions():
        seed = args.first_seed + rep
        data = held_out_data(context, seed, args.val_from)
        for suffix in rotated(list(recipes), rep):
            n, tune = recipes[suffix]
            recipe = dataclasses.replace(config, finalist_steps=n, tune_steps=tune).finalist_recipe()
            trained, loss = {}, {}
            for name in rotated(list(networks), rep):
                t0 = time.perf_counter()
                got = retrained(networks[name], recipe, seed, data, context)
                trained[name] = got.loss_inputs
                loss[name], last = anytime_loss(got.costs, got.errors, context.budgets[0]), got.errors[-1]
                bench.add(f"{name}_anytime_{suffix}", loss[name])
                bench.add(f"{name}_last_{suffix}", last)
                bench.add(f"{name}_early_{suffix}", early_error(got.candidate, got.errors, config))
                bench.add(f"{name}_early_to_last_{suffix}", early_to_last(got.candidate, got.errors, config))
                print(f"  seed {seed}, {n}+{tune} steps: {name} anytime {loss[name]:.4f}, last path {last:.4f} "
                      f"({time.perf_counter() - t0:.0f} s); as shipped, by path {[round(e, 4) for e in got.errors]} "
                      f"at {[round(c, 1) for c in got.costs]}"
                      + "".join(f"; {d.describe(config.metric)}" for d in got.dropped), flush=True)
            for name in networks:
                if name != "paper":
                    figure = f"ratio_{suffix}" if name == "winner" else f"ratio_{name}_{suffix}"
                    bench.add(figure, loss[name] / loss[reference_of(name, networks)])
            floor = floor_steps(trained)
            bench.add(f"floor_ratio_{suffix}", anytime_loss(*floor, context.budgets[0]) / loss["paper"])
            print(f"  bound: the most accurate path {floor[1][1]:.4f} as if ready at {floor[0][1]:.1f}", flush=True)
    bench.finish()


CASES = (Case(bench_held_out), Case(bench_early_path_levers, named_only=True),
         Case(bench_self_distillation, named_only=True), Case(bench_first_paths, named_only=True))

if __name__ == "__main__":
    run_suite(CASES)
