"""The resolution question: a study estimates at a small training size (64x64) and deploys at another
(224x224). What does that cost, and how is a network best made ready for the deployment size?

1. Ways to get a network that works at the deployment size, at equal wall time on this machine, for the
   paper design (each repetition a training seed; the variants interleaved within it):
   ``small`` (all steps at the training size, measured at the deployment size: what a study reported
   before), ``tuned`` (the finalists' recipe: most steps small, then ``--tune-steps`` at the deployment
   size), ``deploy`` (every step at the deployment size, as many as the time allows) and
   ``progressive`` (training size, then halfway, then the deployment size, a third of the time each).
   Figures: each variant's anytime loss (tx2, U(0, 33 ms), costed at the deployment size) and last
   path's RMSE, measured at the deployment size on the first 96 validation frames.
2. Ranking transfer: candidates of the space (the fidelity benchmark's, a fixed seed) trained with the
   finalists' recipe, measured at the training size before their tuning and at the deployment size
   after it: Kendall tau and top-3 agreement between the two rankings of anytime loss. One training
   seed (the trainings are what the time goes to); the small-size figures are those a study ranked by.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from typing import Sequence

import torch

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import SearchSpace, paper_candidate
from explorer.study.config import SearchConfig
from explorer.training.deployment import DeploymentData
from explorer.training.train import evaluate, train

from benchmarks.harness import Bench, Case, run_suite

BUDGET = "time:uniform:33ms"
VAL_FRAMES = 96


def anytime(candidate, rmse: list[float], size) -> float:
    cost = candidate_cost(candidate, tuple(size)).path_costs(get_device("tx2"), "time")
    return anytime_loss(cost, rmse, BUDGET)


def step_seconds(data: DeploymentData, recipe, sizes, steps: int = 5) -> dict:
    """Seconds a training step of the paper design takes at each of ``sizes`` (the median after two)."""
    out = {}
    for size in sizes:
        sets = data.train if tuple(size) == tuple(recipe.train.input_size) else data.deploy_train
        if tuple(size) not in (tuple(recipe.train.input_size), tuple(recipe.deploy_size)):
            sets = open_dataset("synthetic", "train", size, seed=0)
        marks = {}
        cfg = dataclasses.replace(recipe.train, steps=steps, input_size=tuple(size))
        train(build_network(paper_candidate()), sets, [], cfg,
              progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()))
        times = [marks[b] - marks[a] for a, b in zip(sorted(marks), sorted(marks)[1:]) if a >= 2]
        out[tuple(size)] = statistics.median(times)
    return out


def variants(recipe, speeds: dict, middle: tuple[int, int]) -> dict:
    """Each variant's phases, (size, steps), sized to the time of the finalists' recipe."""
    small, deploy = tuple(recipe.train.input_size), tuple(recipe.deploy_size)
    budget = recipe.train.steps * speeds[small] + recipe.tune_steps * speeds[deploy]
    third = budget / 3
    return {
        "small": [(small, round(budget / speeds[small]))],
        "tuned": [(small, recipe.train.steps), (deploy, recipe.tune_steps)],
        "deploy": [(deploy, round(budget / speeds[deploy]))],
        "progressive": [(small, round(third / speeds[small])), (middle, round(third / speeds[middle])),
                        (deploy, round(third / speeds[deploy]))],
    }


def train_phases(phases, base, seed: int, sets: dict, val) -> list[float]:
    """The paper design trained through ``phases`` (each continues the last, at its size; the learning
    rate decays over each phase, a quarter of the recipe's after the first), measured on ``val``."""
    torch.manual_seed(seed)
    net = build_network(paper_candidate())
    for i, (size, steps) in enumerate(phases):
        lr = base.lr if i == 0 else base.lr / 4
        cfg = dataclasses.replace(base, steps=steps, input_size=size, lr=lr, lr_end=lr / 10, seed=seed)
        train(net, sets[size], [], cfg)
    return [float(x) for x in evaluate(net, val, limit=VAL_FRAMES)["rmse"]]


def bench_resolution(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_resolution", "resolution: estimating small, deploying large", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=8, help="candidates of the ranking transfer (default 8)")
    ap.add_argument("--tune-steps", type=int, default=20)
    args = bench.parse_args(ap, argv)
    config = SearchConfig(study="bench", tune_steps=args.tune_steps)
    recipe = config.finalist_recipe()
    small, deploy = tuple(config.train_size), tuple(config.input_size)
    middle = tuple((a + b) // 2 // 32 * 32 for a, b in zip(small, deploy))
    data = DeploymentData(open_dataset("synthetic", "train", small, seed=0),
                          open_dataset("synthetic", "train", deploy, seed=0),
                          open_dataset("synthetic", "val", deploy, train_augment=False))
    sets = {small: data.train, deploy: data.deploy_train, middle: open_dataset("synthetic", "train", middle, seed=0)}
    speeds = step_seconds(data, recipe, [small, middle, deploy])
    plan = variants(recipe, speeds, middle)
    print("step seconds:", {f"{h}x{w}": round(s, 3) for (h, w), s in speeds.items()})
    print("variants:", {k: [f"{s}@{h}x{w}" for (h, w), s in v] for k, v in plan.items()})
    for name in plan:
        bench.figure(f"anytime_{name}", f"paper design, {name}: anytime loss at {deploy[0]}x{deploy[1]}", "m",
                     better="lower")
        bench.figure(f"last_rmse_{name}", f"paper design, {name}: last path's RMSE at {deploy[0]}x{deploy[1]}", "m",
                     better="lower")
    bench.figure("tau_small_to_deploy", f"Kendall tau, {args.candidates} candidates: anytime loss at the training size "
                 "(before tuning) against at the deployment size (after)", "", better="higher")
    bench.figure("top3_shared", "of the 3 best at the training size, how many are among the 3 best at the deployment "
                 "size", "", better="higher")
    ranked = None
    for rep in bench.repetitions():
        for name in _rotated(list(plan), rep):
            rmse = train_phases(plan[name], recipe.train, rep, sets, data.deploy_val)
            bench.add(f"anytime_{name}", anytime(paper_candidate(), rmse, deploy))
            bench.add(f"last_rmse_{name}", rmse[-1])
        if ranked is None:   # one seed of trainings; repeated as a figure so that every repetition has it
            ranked = ranking_transfer(config, recipe, data, args.candidates)
        bench.add("tau_small_to_deploy", ranked[0])
        bench.add("top3_shared", ranked[1])
    bench.finish()


def _rotated(names: list[str], rep: int) -> list[str]:
    k = rep % len(names)
    return names[k:] + names[:k]


def ranking_transfer(config: SearchConfig, recipe, data: DeploymentData, count: int) -> tuple[float, int]:
    """(Kendall tau, shared top 3) between ``count`` candidates' anytime losses at the training size
    (after the recipe's first phase) and at the deployment size (after its tuning)."""
    from scipy.stats import kendalltau
    space = SearchSpace.from_yaml(config.space)
    small_val = open_dataset(config.data, "val", config.train_size, train_augment=False)
    at_small, at_deploy = [], []
    for candidate in space.random_candidates(count, seed=7):
        torch.manual_seed(0)
        net = build_network(candidate)
        train(net, data.train, [], recipe.train)
        rmse_small = [float(x) for x in evaluate(net, small_val, limit=VAL_FRAMES)["rmse"]]
        tuned = train(net, data.deploy_train, data.deploy_val, recipe.tune_config(), val_limit=VAL_FRAMES)
        at_small.append(anytime(candidate, rmse_small, config.input_size))
        at_deploy.append(anytime(candidate, [float(x) for x in tuned.metrics["rmse"]], config.input_size))
        print(f"  {candidate.key}: anytime loss {at_small[-1]:.4f} at the training size, {at_deploy[-1]:.4f} deployed")
    tau = float(kendalltau(at_small, at_deploy).statistic)
    best = lambda xs: set(sorted(range(len(xs)), key=xs.__getitem__)[:3])  # noqa: E731
    return tau, len(best(at_small) & best(at_deploy))


CASES = (Case(bench_resolution),)

if __name__ == "__main__":
    run_suite(CASES)
