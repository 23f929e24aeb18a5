"""Would a whole network run first at a lower resolution, before the full-resolution one, give an
anytime network accurate early paths?

A search's winner has its paths before 9 ms on the TX2 in a LiDAR-only exit and exits in the image
encoder, on shallow features: after training long they stay far above its last path's error, and larger
heads or self-distillation did not change that (``bench_early_path_levers``). A network of the space run
on a smaller image costs less than the same network at the deployment size, but keeps every layer: its
early output is the work of a full encoder and decoder. This experiment measures what chaining the two
would give, before the space has such a dimension: network A, trained for the lower size (``--size``,
default half the study's deployment size) and its depth maps resized up (bilinear) to the deployment
size, then network B at the deployment size, started when A is done. A's paths are measured against the
deployment-size ground truth, B's as the held-out experiment measures them; each network ships as the
study's rule has it (an exit no more accurate than an earlier path left out, A's paths counting before
B's), and the chain's paths are costed on the study's device for its budget, B's after A's last.

Each repetition is one training seed (the held-out experiment's recipe and validation frames: those the
study did not choose with). Figures per recipe (suffix as ``experiments.held_out``'s): the anytime loss of
the paper design and the study's winner at the deployment size (``<B>_anytime_N``), of each A alone
(``low_<A>_anytime_N``, its last path's error ``low_<A>_last_N``) and of each chain
(``chain_<A>_<B>_anytime_N``), every one over the paper design's (``ratio_...``), and the early-to-last
ratio of each (``..._early_to_last_N``: the mean error of the paths ready before 9 ms on the TX2 over the
last path's). ``chain_<A>_<B>_to_<B>_N`` is the chain's anytime loss over B's alone: below 1, the first
pass earns its time. A first network trains at the study's training size, then tunes at the lower size;
``@HxW`` after its name trains it at another size (``winner@32x32``: at the lower size's share of the
training size, as the network would see its frames if it resized them itself).

    python -m experiments.low_res_pass --study tx2-anytime_depth [--steps 300] [--reps 3]
        [--networks winner,paper] [--first winner,paper,winner@32x32] [--size 112x112]

Run it after ``make search`` (whose study it reads, from ``reports/``, untouched).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Subset

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.metrics import MetricAverager, batch_depth_metrics
from explorer.model import build_network
from explorer.model.shipped import ship
from explorer.space import Candidate
from explorer.training.deployment import DeploymentData, train_for_deployment
from explorer.training.train import batch_row, evaluated_frames, image_batch

from benchmarks.harness import Bench, Case, image_size, rotated, run_suite
from experiments.held_out import parse_recipes
from experiments.lib.retraining import (EARLY_MS, Network, Retrained, add_study_options, held_out_data, open_study,
                                        resolve_networks, retrained)


@dataclasses.dataclass(frozen=True)
class Chain:
    """Paths in the order they are ready (path 0, the scan, first): their costs on the study's device for
    its budget, on the TX2 in milliseconds (the early-to-last ratio), and their errors."""

    costs: list[float]
    tx2_ms: list[float]
    errors: list[float]

    def early_to_last(self) -> float:
        early = [e for c, e in zip(self.tx2_ms[1:], self.errors[1:]) if c < EARLY_MS]
        return sum(early) / len(early) / self.errors[-1] if early else float("nan")


def upsampled_errors(net: torch.nn.Module, low_val, full_val, metric: str) -> list[float]:
    """``net``'s per-path ``metric`` on ``low_val``'s frames, each depth map resized (bilinear) to its
    frame in ``full_val`` (the same frames at the deployment size) and scored against that ground truth."""
    net.eval()
    averagers = [MetricAverager() for _ in range(net.candidate.num_paths)]
    with torch.no_grad():
        for low, full in zip(DataLoader(low_val, batch_size=8), DataLoader(full_val, batch_size=8)):
            target = full["depth"]
            for p, out in enumerate(net(image_batch(low, None), low["scan"], batch_row(low))):
                up = F.interpolate(out.float(), size=tuple(target.shape[-2:]), mode="bilinear", align_corners=False)
                for m in batch_depth_metrics(up.reshape(target.shape), target):
                    averagers[p].add(m)
    return [a.result()[metric] for a in averagers]


def trained_low(network: Network, recipe, seed: int, data: DeploymentData, full_val, metric: str) -> list[float]:
    """``network`` trained from scratch with ``recipe`` (deployed at the lower size) and ``seed``, its paths
    measured at the deployment size."""
    torch.manual_seed(seed)
    net = build_network(network.candidate)
    recipe = dataclasses.replace(recipe, train=dataclasses.replace(recipe.train, seed=seed,
                                                                   self_distill=network.distill))
    train_for_deployment(net, data, recipe, torch.device("cpu"))
    return upsampled_errors(net, data.deploy_val, full_val, metric)


def chained(scan: float, first: Candidate | None, first_errors: list[float], then: Retrained | None,
            low: tuple[int, int], full: tuple[int, int], context) -> Chain:
    """Path 0, the scan at the deployment size (its error ``scan``), then the network ``first`` at size
    ``low`` (its per-path errors at the deployment size), then ``then`` (as it ships alone, at ``full``),
    each shipped anew: an exit not below every path before it, in either network, is left out. Either
    network may be None (the other alone)."""
    device, kind = context.device, context.budgets[0].kind
    tx2 = get_device("tx2")
    costs, ms, errors = [0.0], [0.0], [scan]
    for candidate, path_errors, size in ((first, first_errors, low), (then and then.candidate, then and then.errors, full)):
        if candidate is None:
            continue
        shipped = ship(candidate, [min(errors)] + list(path_errors[1:]))
        cost = candidate_cost(shipped.candidate, size)
        start, start_ms = costs[-1], ms[-1]
        costs += [start + c for c in cost.path_costs(device, kind)[1:]]
        ms += [start_ms + c for c in cost.path_costs(tx2, "time")[1:]]
        errors += shipped.losses(path_errors)[1:]
    return Chain(costs, ms, errors)


def resolve_first(text: str, study, context) -> tuple[dict[str, Network], dict[str, tuple[int, int]]]:
    """``--first``: specs as ``--networks`` takes them, each with ``@HxW`` for a training size other than the
    study's -> ({figure name: network}, {figure name: its training size}); a size adds ``_trainHxW`` to
    the name."""
    networks, sizes = {}, {}
    for spec in filter(None, (part.strip() for part in text.split(","))):
        base, at, size_text = spec.partition("@")
        try:
            size = image_size(size_text) if at else tuple(context.config.train_size)
        except ValueError:
            raise SystemExit(f"--first: {size_text!r} in {spec!r} is not a size HxW") from None
        (name, network), = ((k, v) for k, v in resolve_networks(f"paper,{base}", study, context).items()
                            if k != "paper" or base.strip() == "paper")
        name += f"_train{size[0]}x{size[1]}" if at else ""
        networks[name], sizes[name] = network, size
    if not networks:
        raise SystemExit("--first: name at least one network")
    return networks, sizes


def declare(bench: Bench, recipes, networks, first, unit: str) -> None:
    for suffix, (n, tune) in recipes.items():
        recipe = f"{n} steps + {tune} at the deployment size (the lower size for a first pass)"
        names = [*networks, *(f"low_{a}" for a in first), *(f"chain_{a}_{b}" for a in first for b in networks)]
        for name in names:
            bench.figure(f"{name}_anytime_{suffix}", f"{name}: anytime loss, {recipe}", unit, better="lower")
            if name != "paper":
                bench.figure(f"ratio_{name}_{suffix}", f"{name} / paper design, anytime loss, {recipe}", "",
                             better="lower")
            bench.figure(f"{name}_early_to_last_{suffix}", f"{name}: mean error of its paths ready before "
                         f"{EARLY_MS:g} ms on tx2 over its last path's, {recipe}", "x", better="lower")
        for a in first:
            bench.figure(f"low_{a}_last_{suffix}", f"low_{a}: last path's error at the deployment size, {recipe}",
                         unit, better="lower")
            for b in networks:
                bench.figure(f"chain_{a}_{b}_to_{b}_{suffix}", f"chain {a} then {b} / {b} alone, anytime loss, "
                             f"{recipe}", "", better="lower")


def bench_low_res_pass(argv: Sequence[str] | None = None) -> None:
    """Would a whole network run first at a lower resolution give accurate early paths? A study's winner
    and the paper design at the deployment size, each network also trained for half that size and run
    first, alone and chained before each full-size network, retrained on the same seeds and measured on
    validation frames the study did not use."""
    bench = Bench("bench_low_res_pass", "a low-resolution first pass before the full-resolution network",
                  __doc__)
    run_low_res_pass(bench, argv, "winner,paper", "winner,paper")


def bench_low_res_train_size(argv: Sequence[str] | None = None) -> None:
    """Must a network that works at half the deployment size also train at half the training size, as it
    would if it resized its frames itself? The study's winner as a first pass at half the deployment size,
    trained at the study's training size and at half of it, beside the paper design, on the same seeds."""
    bench = Bench("bench_low_res_train_size", "a low-resolution network trained at the training size or at "
                  "its share of it", bench_low_res_train_size.__doc__)
    run_low_res_pass(bench, argv, "paper", "winner,winner@32x32")


def record_chains(bench: Bench, suffix: str, first: dict[str, Network], whole: dict[str, Retrained],
                  low_errors: dict[str, list[float]], sizes: tuple[tuple[int, int], tuple[int, int]], context) -> None:
    """One recipe's figures: every network at the deployment size (``whole``), every first pass alone
    (``low_errors``) and every chain of the two, scored as they ship; ``sizes``: (lower, deployment)."""
    low, full = sizes
    scan = whole["paper"].errors[0]
    chains = {b: chained(scan, None, [], whole[b], low, full, context) for b in whole}
    chains |= {f"low_{a}": chained(scan, first[a].candidate, low_errors[a], None, low, full, context)
               for a in first}
    chains |= {f"chain_{a}_{b}": chained(scan, first[a].candidate, low_errors[a], whole[b], low, full, context)
               for a in first for b in whole}
    loss = {name: anytime_loss(c.costs, c.errors, context.budgets[0]) for name, c in chains.items()}
    for name, chain in chains.items():
        bench.add(f"{name}_anytime_{suffix}", loss[name])
        bench.add(f"{name}_early_to_last_{suffix}", chain.early_to_last())
        if name != "paper":
            bench.add(f"ratio_{name}_{suffix}", loss[name] / loss["paper"])
        print(f"  {name}: anytime {loss[name]:.4f}, paths {[round(e, 4) for e in chain.errors]} at "
              f"{[round(c, 1) for c in chain.costs]}", flush=True)
    for a in first:
        bench.add(f"low_{a}_last_{suffix}", chains[f"low_{a}"].errors[-1])
        for b in whole:
            bench.add(f"chain_{a}_{b}_to_{b}_{suffix}", loss[f"chain_{a}_{b}"] / loss[b])


def run_low_res_pass(bench: Bench, argv: Sequence[str] | None, networks: str, first: str) -> None:
    """Retrains, per seed, the networks at the deployment size and the first passes (the defaults of
    ``--networks`` and ``--first``: ``networks`` and ``first``) and records the figures ``declare`` names."""
    ap = bench.parser()
    ap.add_argument("--steps", default="300", help="recipes, as experiments.held_out takes them (default 300)")
    ap.add_argument("--networks", default=networks, help="the networks at the deployment size, as "
                    "experiments.held_out names them; paper among them (default %(default)s)")
    ap.add_argument("--first", default=first, help="the networks run first at the lower size, named "
                    "the same way, each with @HxW where it trains at another size than the study's training size "
                    "(winner@32x32) (default %(default)s)")
    ap.add_argument("--size", type=image_size, help="the first pass's input size, HxW (default: half the "
                    "study's deployment size)")
    add_study_options(ap)
    args = bench.parse_args(ap, argv)
    study, context = open_study(args)
    config = context.config
    full = tuple(config.input_size)
    low = tuple(args.size) if args.size else (full[0] // 2, full[1] // 2)
    networks = resolve_networks(args.networks, study, context)
    first, first_train = resolve_first(args.first, study, context)
    recipes = parse_recipes(args.steps, config)
    declare(bench, recipes, networks, first, "m" if config.metric in ("rmse", "mae") else "")
    val = open_dataset(config.data, "val", full, train_augment=False)
    val_from = evaluated_frames(val, config.val_limit)
    bench.note(f"study {args.study}: {', '.join(f'{k} {n.candidate.key}' for k, n in networks.items())}; first "
               f"pass at {low[0]}x{low[1]}: {', '.join(f'{k} {n.candidate.key}' for k, n in first.items())}; "
               f"{config.device}, {config.budgets[0]}; deployment size {full[0]}x{full[1]}; measured on validation "
               f"frames {val_from} to {len(val) - 1} of {config.data}; seeds {args.first_seed} on; cpu, torch "
               f"threads {args.threads}")

    for rep in bench.repetitions():
        seed = args.first_seed + rep
        data = held_out_data(context, seed, val_from)
        low_val = Subset(open_dataset(config.data, "val", low, train_augment=False), range(val_from, len(val)))
        low_train = open_dataset(config.data, "train", low, seed=seed)
        trains = {size: open_dataset(config.data, "train", size, seed=seed) for size in set(first_train.values())}
        low_data = {a: DeploymentData(trains[first_train[a]], low_train, low_val) for a in first}
        for suffix in rotated(list(recipes), rep):
            n, tune = recipes[suffix]
            recipe = dataclasses.replace(config, finalist_steps=n, tune_steps=tune).finalist_recipe()
            low_recipe = dataclasses.replace(recipe, deploy_size=low)
            low_recipe = {a: dataclasses.replace(low_recipe, train=dataclasses.replace(low_recipe.train, input_size=size))
                          for a, size in first_train.items()}
            whole, low_errors = {}, {}
            for kind, name in rotated([("full", b) for b in networks] + [("low", a) for a in first], rep):
                t0 = time.perf_counter()
                if kind == "full":
                    whole[name] = retrained(networks[name], recipe, seed, data, context)
                    got = whole[name].errors
                else:
                    low_errors[name] = got = trained_low(first[name], low_recipe[name], seed, low_data[name], data.deploy_val,
                                                         config.metric)
                print(f"  seed {seed}, {n}+{tune}: {name} at {low if kind == 'low' else full}, by path "
                      f"{[round(e, 4) for e in got]} ({time.perf_counter() - t0:.0f} s)", flush=True)
            record_chains(bench, suffix, first, whole, low_errors, (low, full), context)
    bench.finish()


CASES = (Case(bench_low_res_pass), Case(bench_low_res_train_size, named_only=True))

if __name__ == "__main__":
    run_suite(CASES)
