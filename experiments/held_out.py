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
early-to-last ratio (``<name>_early_to_last_N``): the mean error of its paths ready before 9 ms on the
TX2 over its last path's. A network beside the winner and
the paper design adds ``ratio_<name>_N``, its anytime loss over the paper design's trained with the
same weights when that is measured too (``paper:weights=anytime``), else the plain one's (``<name>``:
the spec, punctuation as underscores).

    python -m experiments.held_out --study tx2-anytime_depth [--steps 300,2000+130] [--reps 3]
        [--networks winner,paper,winner:encoder_blocks=11,winner:weights=anytime,paper:weights=anytime]

Run it after ``make search`` (whose study it reads, from ``reports/``, untouched).
"""

from __future__ import annotations

import dataclasses
import re
import time
from pathlib import Path
from typing import Sequence

import torch
import yaml
from torch.utils.data import Subset

from explorer.anytime import anytime_loss, exit_loss_weights
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.errors import UserError
from explorer.model import build_network
from explorer.space import Candidate, paper_candidate
from explorer.study import trial_record
from explorer.study.config import SearchConfig, StudyContext, study_context
from explorer.study.results import winner
from explorer.study.storage import load_study
from explorer.supernet import largest_candidate
from explorer.training.deployment import DeploymentData, DeploymentRecipe, train_for_deployment
from explorer.training.train import evaluated_frames

from benchmarks.harness import Bench, Case, rotated, run_suite
from experiments.lib.comparison import floor_steps

def held_out_data(context: StudyContext, seed: int, val_from: int) -> DeploymentData:
    """The study's training frames (at its training and deployment sizes, augmented with ``seed``) and
    its validation frames from ``val_from`` on, at the deployment size."""
    config = context.config
    val = open_dataset(config.data, "val", config.input_size, train_augment=False)
    if val_from >= len(val):
        raise SystemExit(f"--val-from {val_from}: the validation set has {len(val)} frames")
    return DeploymentData(open_dataset(config.data, "train", config.train_size, seed=seed),
                          open_dataset(config.data, "train", config.input_size, seed=seed),
                          Subset(val, range(val_from, len(val))))


#: how each exit's training loss is weighted (``:weights=``): equal, or by its share of the anytime loss
WEIGHTINGS = ("equal", "anytime")


@dataclasses.dataclass(frozen=True)
class Network:
    """What ``--networks`` names: a candidate, how its exits' losses are weighted in training, and the
    weight of self-distillation (``explorer train --self-distill``)."""

    candidate: Candidate
    weights: str = "equal"
    distill: float = 0.0

    @property
    def training(self) -> tuple[str, float]:
        return self.weights, self.distill


def retrained(network: Network, recipe: DeploymentRecipe, seed: int, data: DeploymentData,
              context: StudyContext) -> tuple[list[float], list[float]]:
    """``network`` trained from scratch with ``recipe`` and ``seed``: (its paths' costs on the study's
    device for its first budget's kind, their errors measured on ``data``'s validation frames)."""
    config, budget = context.config, context.budgets[0]
    costs = candidate_cost(network.candidate, tuple(config.input_size)).path_costs(context.device, budget.kind)
    weights = exit_loss_weights(costs, budget) if network.weights == "anytime" else None
    torch.manual_seed(seed)
    net = build_network(network.candidate)
    recipe = dataclasses.replace(recipe, train=dataclasses.replace(recipe.train, seed=seed, exit_weights=weights,
                                                                   self_distill=network.distill))
    result = train_for_deployment(net, data, recipe, torch.device("cpu"))
    errors = [float(x) for x in result.metrics[config.metric]]
    return [float(c) for c in costs], errors


#: a path ready before this on the TX2 is an early one (the early-to-last ratio)
EARLY_MS = 9.0


def early_to_last(network: Network, errors: list[float], config: SearchConfig) -> float:
    """The mean error of ``network``'s paths (past the scan) ready before EARLY_MS on the TX2, over its last
    path's (NaN where none is ready that early)."""
    ms = candidate_cost(network.candidate, tuple(config.input_size)).path_costs(get_device("tx2"), "time")
    early = [e for c, e in zip(ms[1:], errors[1:]) if c < EARLY_MS]
    return sum(early) / len(early) / errors[-1] if early else float("nan")


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


def resolve_networks(text: str, study, context: StudyContext) -> dict[str, Network]:
    """``--networks``: specs ``BASE[:FIELD=VALUE...]`` -> {figure name: network}. BASE is ``winner``,
    ``paper``, ``largest`` or a candidate YAML file; each FIELD=VALUE changes one field of it (a YAML
    value: ``encoder_blocks=11``, ``decoder_widths=[1024,256,64,32]``), or its training's exit weights
    (``weights=anytime``)."""
    specs = [part.strip() for part in re.split(r",(?![^\[]*\])", text) if part.strip()]   # not in [...]
    if "paper" not in specs:
        raise SystemExit("--networks: include paper (every ratio is to the paper design)")
    networks = {}
    for spec in specs:
        base, *changes = spec.split(":")
        candidate = _base_network(base, study, context)
        name = Path(base).stem if base.endswith((".yaml", ".yml")) else base
        fields, weights, distill = candidate.to_dict(), "equal", 0.0
        for change in changes:
            field, equals, value = change.partition("=")
            if not equals or not field:
                raise SystemExit(f"--networks: {change!r} in {spec!r} is not FIELD=VALUE")
            if field.strip() == "distill":
                try:
                    distill = float(value)
                except ValueError:
                    raise SystemExit(f"--networks: distill={value} in {spec!r} is not a number") from None
            elif field.strip() == "weights":
                if value.strip() not in WEIGHTINGS:
                    raise SystemExit(f"--networks: weights={value} in {spec!r}: use one of {', '.join(WEIGHTINGS)}")
                weights = value.strip()
            else:
                try:
                    fields[field.strip()] = yaml.safe_load(value)
                except yaml.YAMLError:
                    raise SystemExit(f"--networks: {value!r} in {spec!r} is not a YAML value") from None
            name += "_" + "_".join(filter(None, re.split(r"[^0-9A-Za-z]+", change)))
        try:
            networks[name] = Network(Candidate.from_dict(fields, source=f"--networks {spec}"), weights, distill)
        except UserError as exc:
            raise SystemExit(str(exc)) from None
    return networks


def reference_of(name: str, networks: dict[str, Network]) -> str:
    """The paper design a network's ratio is taken over: the one trained with the same exit weights when it
    is measured (and the network is not a paper design itself), else the plain one."""
    network, paper = networks[name], paper_candidate()
    if network.candidate == paper:
        return "paper"
    return next((other for other, n in networks.items() if n.candidate == paper and n.training == network.training),
                "paper")


def _base_network(base: str, study, context: StudyContext) -> Candidate:
    if base == "winner":
        best = winner(study)
        if best is None:
            raise SystemExit("the study has no winner yet: let its search finish first")
        return Candidate.from_dict(trial_record(best).candidate)
    if base == "paper":
        return paper_candidate()
    if base == "largest":
        return largest_candidate(context.space)
    if base.endswith((".yaml", ".yml")) and Path(base).is_file():
        return Candidate.from_yaml(base)
    raise SystemExit(f"--networks: {base!r} is not winner, paper, largest or a candidate YAML file")


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
            bench.figure(f"{name}_early_to_last_{suffix}", f"{name}: mean {metric} of its paths ready before "
                         f"{EARLY_MS:g} ms on tx2 over its last path's, {recipe}", "x", better="lower")


def bench_held_out(argv: Sequence[str] | None = None) -> None:
    """The experiment (the module's docstring says what it asks)."""
    bench = Bench("bench_held_out", "a study's winner against the paper design in held-out retraining, by recipe "
                  "length", __doc__)
    ap = bench.parser()
    ap.add_argument("--study", default="tx2-anytime_depth", help="the finished study (default tx2-anytime_depth)")
    ap.add_argument("--reports", type=Path, default=Path("reports"), help="its reports folder (default reports)")
    ap.add_argument("--steps", default="300,2000+130", help="recipes, comma-separated: N steps at the training "
                    "size then the study's tuning steps, or N+T for T tuning steps (default 300,2000+130: the "
                    "finalists' recipe, and one about 7 times as long with the same share of tuning)")
    ap.add_argument("--first-seed", type=int, default=100, help="the first repetition's training seed, the next "
                    "ones following it (default 100)")
    ap.add_argument("--val-from", type=int, help="the first validation frame measured (default: the first after "
                    "those the study measured its finalists on)")
    ap.add_argument("--networks", default="winner,paper", help="what to retrain, comma-separated: winner, paper, "
                    "largest (the largest network of the study's space) or candidate YAML files, each with "
                    ":FIELD=VALUE changes if any (winner:encoder_blocks=11), :weights=anytime to weight its exits' "
                    "training losses by their share of the anytime loss, :distill=W for self-distillation of weight W; paper "
                    "among them (default winner,paper)")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    args = bench.parse_args(ap, argv)
    torch.set_num_threads(args.threads)

    study = load_study(args.study, None, args.reports)
    context = study_context(study)
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
                trained[name] = retrained(networks[name], recipe, seed, data, context)
                loss[name], last = anytime_loss(*trained[name], context.budgets[0]), trained[name][1][-1]
                bench.add(f"{name}_anytime_{suffix}", loss[name])
                bench.add(f"{name}_last_{suffix}", last)
                bench.add(f"{name}_early_to_last_{suffix}", early_to_last(networks[name], trained[name][1], config))
                print(f"  seed {seed}, {n}+{tune} steps: {name} anytime {loss[name]:.4f}, last path {last:.4f} "
                      f"({time.perf_counter() - t0:.0f} s); by path {[round(e, 4) for e in trained[name][1]]} at "
                      f"{[round(c, 1) for c in trained[name][0]]}", flush=True)
            for name in networks:
                if name != "paper":
                    figure = f"ratio_{suffix}" if name == "winner" else f"ratio_{name}_{suffix}"
                    bench.add(figure, loss[name] / loss[reference_of(name, networks)])
            floor = floor_steps(trained)
            bench.add(f"floor_ratio_{suffix}", anytime_loss(*floor, context.budgets[0]) / loss["paper"])
            print(f"  bound: the most accurate path {floor[1][1]:.4f} as if ready at {floor[0][1]:.1f}", flush=True)
    bench.finish()


CASES = (Case(bench_held_out),)

if __name__ == "__main__":
    run_suite(CASES)
