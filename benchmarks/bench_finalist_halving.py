"""Successive halving over the estimate's best, against the finalists the study retrains now, at about
the same retraining time. Each repetition is one seed: ``make search``'s supernet and sampling (no time
limit, no finalists), then from its estimates

- ``default``: the finalists ``explorer search`` retrains (``choose_finalists``: the best estimate,
  then the best of each other image encoder; ``--finalists``, default 3), each with the finalists'
  recipe (300 steps at the training size, then the tuning at the deployment size); the best measured one
  is the winner;
- ``halving``: ``--pool`` candidates chosen the same way (default 6) trained with the same recipe's
  first half (its schedule, stopped at the middle), ranked there by their anytime loss measured at the
  training size (no tuning: that is what makes a rung cheap), the best ``--keep`` (default 2) continued
  to the end of the recipe and tuned, the best measured one the winner. With tuning costing about as much
  as a finalist's training, 6 half-trainings and 2 continuations cost about what 3 finalists do; the
  record holds both strategies' seconds, as measured here, to check it;
- ``pool_best``: every pool candidate retrained in full, the best measured one: what a perfect first
  rung would keep (twice the default's time; a bound, not a strategy).

Every pool candidate is trained once, its rung measured on the way (the same schedule and seed as the
full recipe, so continuing a rung is training in full). Then each seed's winners and the paper design are
retrained with one longer recipe (``--final-steps``, default 600, then the same tuning), with that
seed, and measured at the deployment size on the first 96 validation frames, as in bench_search_value.
Figures: each winner's anytime loss over the paper design's (``ratio_<strategy>``), the halving's
lead over the default in the same seed, whether both chose the same network, how well the estimate
and the rung order the pool (Kendall tau against the full recipe's anytime loss), and the seconds each
strategy's retrainings took.

    OMP_NUM_THREADS=1 python benchmarks/bench_finalist_halving.py [--reps 3] [--pool 6] [--keep 2]
        [--finalists 3] [--final-steps 600] [--first-seed 0]
"""

from __future__ import annotations

import dataclasses
import gc
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from scipy.stats import kendalltau

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_search_value import (SAMPLING_CAP_S, VAL_FRAMES, base_config, final_losses,  # noqa: E402
                                final_recipe, final_recipe_note, fresh_cache, prepare, run_seeds)
from harness import Bench  # noqa: E402

from explorer.anytime import anytime_loss  # noqa: E402
from explorer.cost import candidate_cost, get_device  # noqa: E402
from explorer.data import open_dataset  # noqa: E402
from explorer.model import build_network  # noqa: E402
from explorer.space import Candidate, paper_candidate  # noqa: E402
from explorer.study.finalists import choose_finalists  # noqa: E402
from explorer.study.records import trial_record  # noqa: E402
from explorer.study.search import search  # noqa: E402
from explorer.training.deployment import DeploymentData, DeploymentRecipe  # noqa: E402
from explorer.training.memory import release_host_memory  # noqa: E402
from explorer.training.train import train  # noqa: E402

STRATEGIES = ("default", "halving", "pool_best")


@dataclass
class Retrained:
    """One pool candidate through the finalists' recipe: its estimate, its anytime loss at the rung (the
    recipe's middle, at the training size) and at the end (tuned, at the deployment size), and the
    seconds up to the rung, from there to the end of the training size, and of the tuning."""

    candidate: Candidate
    estimate: float
    rung: float
    final: float
    to_rung_s: float
    after_rung_s: float
    tune_s: float


def path_losses_to_anytime(candidate: Candidate, errors: list[float], config) -> float:
    costs = candidate_cost(candidate, tuple(config.input_size)).path_costs(get_device(config.device), "time")
    return anytime_loss(list(costs), errors, config.budgets[0])


def retrain_with_rung(candidate: Candidate, estimate: float, recipe: DeploymentRecipe, data: DeploymentData,
                      val_small, config) -> Retrained:
    """``candidate`` through ``recipe`` as a finalist is (explorer.training.deployment), its paths also
    measured at the training size half-way through the first phase."""
    rung_step = recipe.train.steps // 2
    torch.manual_seed(recipe.train.seed)
    net = build_network(candidate)
    at_rung: dict = {}

    def report(step, metrics) -> None:
        at_rung["errors"] = [float(x) for x in metrics[config.metric]]
        at_rung["time"] = time.perf_counter()

    started = time.perf_counter()
    train(net, data.train, val_small, dataclasses.replace(recipe.train, eval_every=rung_step), torch.device("cpu"),
          report=report, val_limit=VAL_FRAMES)
    trained = time.perf_counter()
    release_host_memory()
    tuned = train(net, data.deploy_train, data.deploy_val, recipe.tune_config(), torch.device("cpu"),
                  val_limit=VAL_FRAMES)
    final = [float(x) for x in tuned.metrics[config.metric]]
    return Retrained(candidate, estimate, path_losses_to_anytime(candidate, at_rung["errors"], config),
                     path_losses_to_anytime(candidate, final, config), at_rung["time"] - started,
                     trained - at_rung["time"], time.perf_counter() - trained)


def declare(bench: Bench, args) -> None:
    recipe = f"after {args.final_steps} steps + tuning at 224x224"
    for name in STRATEGIES:
        bench.figure(f"ratio_{name}", f"{name}: winner / paper design, anytime loss {recipe}", "", better="lower")
    bench.figure("lead_halving", "ratio_halving - ratio_default in the same seed (above 0: the default's winner "
                 "was better)", "", better="higher")
    bench.figure("same_winner", "halving chose the default's winner (1) or another network (0)", "")
    bench.figure("halving_kept_default_winner", "the default's winner among the networks halving kept (1 or 0)", "")
    bench.figure("tau_estimate", f"Kendall tau over the pool of {args.pool}: the estimate against the "
                 "finalists' recipe", "", better="higher")
    bench.figure("tau_rung", f"Kendall tau over the pool of {args.pool}: the rung (half the recipe, training size) "
                 "against the finalists' recipe", "", better="higher")
    bench.figure("seconds_default", f"default: {args.finalists} finalists retrained", "s")
    bench.figure("seconds_halving", f"halving: {args.pool} to the rung, {args.keep} continued and tuned", "s")
    bench.figure("paper_anytime", f"paper design: anytime loss {recipe}", "m", better="lower")


def estimated(seed: int, args, work: Path, data_cache: Path):
    """``make search``'s supernet and sampling for ``seed`` (no finalists, no time limit), in a fresh cache:
    (the study's settings, its pool, the default's finalists), each candidate with its estimate."""
    name = f"halving-{seed}"
    config = base_config(seed, name, finalists=0)
    reports = work / "reports" / name
    with fresh_cache(work / "cache" / name, data_cache):
        study = search(config, timeout_s=args.sampling_s, reports=reports).study

    def chosen(count: int) -> list[tuple[Candidate, float]]:
        return [(Candidate.from_dict(trial_record(t).candidate), t.values[0]) for t in choose_finalists(study, count)]
    pool, finalists = chosen(args.pool), chosen(args.finalists)
    print(f"  seed {seed}: {len(study.trials)} trials; pool {[c.key for c, _ in pool]}", flush=True)
    gc.unfreeze()   # the search froze what it had loaded (explorer.study.search._optimize): let it go
    gc.collect()
    shutil.rmtree(reports, ignore_errors=True)
    return config, pool, finalists


def one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data: DeploymentData) -> None:
    config, pool, finalists = estimated(seed, args, work, data_cache)
    val_small = open_dataset(config.data, "val", config.train_size, train_augment=False)
    recipe = config.finalist_recipe()
    runs: dict[str, Retrained] = {}
    for candidate, estimate in pool + finalists:
        if candidate.key not in runs:
            runs[candidate.key] = r = retrain_with_rung(candidate, estimate, recipe, data, val_small, config)
            print(f"  {candidate.key}: estimate {r.estimate:.4f}, rung {r.rung:.4f}, final {r.final:.4f} "
                  f"({r.to_rung_s:.0f} + {r.after_rung_s:.0f} + {r.tune_s:.0f} s)", flush=True)
    default = [runs[c.key] for c, _ in finalists]
    pooled = [runs[c.key] for c, _ in pool]
    kept = sorted(pooled, key=lambda r: r.rung)[:args.keep]
    winners = {"default": min(default, key=lambda r: r.final), "halving": min(kept, key=lambda r: r.final),
               "pool_best": min(pooled, key=lambda r: r.final)}
    print("  winners: " + ", ".join(f"{k} {w.candidate.key}" for k, w in winners.items()), flush=True)
    bench.add("same_winner", float(winners["halving"] is winners["default"]))
    bench.add("halving_kept_default_winner", float(any(r is winners["default"] for r in kept)))
    bench.add("tau_estimate", kendalltau([r.estimate for r in pooled], [r.final for r in pooled]).statistic)
    bench.add("tau_rung", kendalltau([r.rung for r in pooled], [r.final for r in pooled]).statistic)
    bench.add("seconds_default", sum(r.to_rung_s + r.after_rung_s + r.tune_s for r in default))
    bench.add("seconds_halving", sum(r.to_rung_s for r in pooled) + sum(r.after_rung_s + r.tune_s for r in kept))

    paper, long = paper_candidate(), final_recipe(args.final_steps)
    trained = final_losses([(c.key, c, long) for c in (paper, *(w.candidate for w in winners.values()))], seed, data)
    budget = config.budgets[0]
    loss = {key: anytime_loss(*trained[key], budget) for key in trained}
    bench.add("paper_anytime", loss[paper.key])
    ratio = {name: loss[w.candidate.key] / loss[paper.key] for name, w in winners.items()}
    for name in STRATEGIES:
        bench.add(f"ratio_{name}", ratio[name])
    bench.add("lead_halving", ratio["halving"] - ratio["default"])


def main() -> None:
    bench = Bench(__file__, "successive halving over the estimate's best against the default finalists", __doc__)
    ap = bench.parser()
    ap.add_argument("--pool", type=int, default=6, help="candidates trained to the rung (default 6)")
    ap.add_argument("--keep", type=int, default=2, help="candidates continued past the rung (default 2)")
    ap.add_argument("--finalists", type=int, default=3, help="the default's finalists (default 3, as make search)")
    ap.add_argument("--final-steps", type=int, default=600, help="steps at the training size of the final "
                    "comparison's recipe, before the tuning (default 600: twice the finalists')")
    ap.add_argument("--sampling-s", type=float, default=SAMPLING_CAP_S,
                    help=f"the search's sampling time (default {SAMPLING_CAP_S:g}, explorer search's)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first repetition's seed (default 0)")
    args = bench.parse_args(ap)
    if not 1 <= args.keep <= args.pool:
        ap.error("--keep must be between 1 and --pool")
    config, data = prepare(args.threads)
    declare(bench, args)
    bench.note(f"cpu, torch threads {args.threads}; make search's supernet ({config.supernet_steps} steps) and "
               f"{args.sampling_s:g} s of sampling a seed; finalists' recipe {config.finalist_steps} steps at "
               f"{config.train_size[0]}x{config.train_size[1]} + {config.tuning_steps} at "
               f"{config.input_size[0]}x{config.input_size[1]}; the rung at step {config.finalist_steps // 2}, "
               f"measured at the training size on {VAL_FRAMES} validation frames; pool {args.pool}, keep {args.keep}, "
               f"default finalists {args.finalists}; seeds {args.first_seed} to {args.first_seed + bench.reps - 1}; "
               f"{final_recipe_note(config, args.final_steps)}; {config.device}, {config.budgets[0]}")
    run_seeds(bench, one_seed, args, data, f"{bench.name}-")
    bench.finish()


if __name__ == "__main__":
    main()
