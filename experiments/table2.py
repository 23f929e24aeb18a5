"""The paper's Table 2 with the explorer's row: for each of its ten columns (TX2 and RPi4; the anytime
loss for a uniform time budget of 100, 50 and 33 ms and a uniform energy budget of 0.5 and 0.25 J), the
network a finished study picks for that column against the paper design, both retrained from scratch
with the study's finalists' recipe and measured at the deployment size on validation frames the study
did not use.

Accuracy does not depend on the device, cost does: a study's estimates are re-scored for each column
(as ``explorer rescore`` does) and the best one is that column's pick, so one search serves every
column, and a network picked by several columns is retrained once per seed. Every network, the paper
design included, ships as the study would ship it (an exit no more accurate than an earlier path left
out, ``explorer.model.shipped``, unless the study kept every exit). Figures per column (``tx2_t33ms``,
``rpi4_e0_25j``, ...): the explorer's anytime loss, the paper design's, and their ratio (below 1 the
explorer's pick is better).

    python -m experiments.table2 --study tx2-anytime_depth [--steps 300] [--reps 3]

Each repetition is one training seed (``--first-seed`` on); the networks train in an order that
rotates. Run it after ``make search`` (whose study it reads, from ``reports/``, untouched).
"""

from __future__ import annotations

import dataclasses
import re
import time
from typing import Sequence


from explorer.anytime import anytime_loss, parse_budget
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.space import Candidate, paper_candidate
from explorer.study import trial_record
from explorer.study.results import scored_trials, trial_anytime_loss
from explorer.training.train import evaluated_frames

from benchmarks.harness import Bench, Case, rotated, run_suite
from experiments.lib.retraining import Network, add_study_options, held_out_data, open_study, retrained

DEVICES = ("tx2", "rpi4")
BUDGETS = ("time:uniform:100ms", "time:uniform:50ms", "time:uniform:33ms", "energy:uniform:0.5J",
           "energy:uniform:0.25J")


def column(device: str, budget: str) -> str:
    """A column's figure name: ``tx2_t33ms``, ``rpi4_e0_25j``."""
    kind, _, limit = budget.split(":")
    return f"{device}_{kind[0]}{re.sub(r'[^0-9a-z]+', '_', limit.lower())}"


def column_picks(study) -> dict[str, Candidate]:
    """Each column's pick: the candidate of the study's best estimate re-scored for that column."""
    estimates = [t for t in scored_trials(study) if trial_record(t).is_estimate and not trial_record(t).baseline
                 and trial_record(t).candidate is not None]
    if not estimates:
        raise SystemExit("the study has no estimates to pick from: let its search finish first")
    picks = {}
    for device in DEVICES:
        profile = get_device(device)
        for budget in BUDGETS:
            best = min(estimates, key=lambda t: trial_anytime_loss(t, profile, budget))
            picks[column(device, budget)] = Candidate.from_dict(trial_record(best).candidate)
    return picks


def shipped_losses(shipped: Candidate, errors: list[float], size: tuple[int, int]) -> dict[str, float]:
    """The anytime loss in every column of the network that ships, given its paths' errors (dropping an
    exit depends on accuracy alone: one network ships for every device)."""
    cost = candidate_cost(shipped, size)
    return {column(device, budget): anytime_loss(cost.path_costs(get_device(device), parse_budget(budget).kind),
                                                 errors, budget)
            for device in DEVICES for budget in BUDGETS}


def bench_table2(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_table2", "The paper's Table 2 with the explorer's row", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, help="steps at the training size (default: the study's finalists'); "
                    "then the study's tuning steps at the deployment size")
    add_study_options(ap)
    args = bench.parse_args(ap, argv)
    study, context = open_study(args)
    config = context.config
    if args.steps is not None:
        config = dataclasses.replace(config, finalist_steps=args.steps)
        context = context.with_config(config)
    picks = column_picks(study)
    networks = {"paper": paper_candidate()}
    for name, candidate in picks.items():
        networks.setdefault(next((n for n, c in networks.items() if c == candidate), f"pick_{candidate.key}"),
                            candidate)
    by_column = {name: next(n for n, c in networks.items() if c == candidate) for name, candidate in picks.items()}
    for device in DEVICES:
        for budget in BUDGETS:
            name = column(device, budget)
            bench.figure(f"explorer_{name}", f"explorer's pick ({picks[name].key}): anytime loss, {device}, {budget}",
                         "m", "lower")
            bench.figure(f"paper_{name}", f"paper design: anytime loss, {device}, {budget}", "m", "lower")
            bench.figure(f"ratio_{name}", f"explorer's pick / paper design, {device}, {budget}", "", "lower")
    val = open_dataset(config.data, "val", config.input_size, train_augment=False)
    val_from = evaluated_frames(val, config.val_limit)
    recipe = config.finalist_recipe()
    size = tuple(config.input_size)
    bench.note(f"study {args.study}; picks by column: " + ", ".join(f"{c} {picks[c].key}" for c in picks)
               + f"; recipe {config.finalist_steps} steps at {config.train_size[0]}x{config.train_size[1]} then "
               f"{config.tuning_steps} at {size[0]}x{size[1]}, measured there on validation frames {val_from} to "
               f"{len(val) - 1} of {config.data}; seeds {args.first_seed} on; cpu, torch threads {args.threads}")
    print(f"{len(networks)} networks to retrain per seed: " + ", ".join(f"{n} ({c.key})" for n, c in networks.items()),
          flush=True)
    for rep in bench.repetitions():
        seed = args.first_seed + rep
        data = held_out_data(context, seed, val_from)
        losses = {}
        for name in rotated(list(networks), rep):
            t0 = time.perf_counter()
            got = retrained(Network(networks[name]), recipe, seed, data, context)
            losses[name] = shipped_losses(got.candidate, got.errors, size)
            errors = got.errors
            print(f"  seed {seed}: {name} by path {[round(e, 4) for e in errors]} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        for col, name in by_column.items():
            bench.add(f"explorer_{col}", losses[name][col])
            bench.add(f"paper_{col}", losses["paper"][col])
            bench.add(f"ratio_{col}", losses[name][col] / losses["paper"][col])
    bench.finish()


CASES = (Case(bench_table2),)

if __name__ == "__main__":
    run_suite(CASES)
