"""Networks retrained from scratch with a study's finalists' recipe and measured on validation frames the
study did not choose with: what the held-out and early-paths experiments share. ``--networks`` specs
(``winner``, ``paper``, ``largest`` or a candidate YAML, each with ``:FIELD=VALUE`` changes,
``:weights=anytime`` and ``:distill=W``) resolve here."""

from __future__ import annotations

import argparse
import dataclasses
import re
from pathlib import Path

import torch
import yaml
from torch.utils.data import Subset

from explorer.anytime import exit_loss_weights
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.errors import UserError
from explorer.model import build_network
from explorer.model.shipped import DroppedExit, ship
from explorer.space import Candidate, paper_candidate
from explorer.study import trial_record
from explorer.study.config import SearchConfig, StudyContext, study_context
from explorer.study.results import winner
from explorer.study.storage import load_study
from explorer.supernet import largest_candidate
from explorer.training.deployment import DeploymentData, DeploymentRecipe, train_for_deployment


def add_study_options(ap: argparse.ArgumentParser) -> None:
    """The options of an experiment on a finished study: which study (read untouched), the first seed, the
    torch threads."""
    ap.add_argument("--study", default="tx2-anytime_depth", help="the finished study (default tx2-anytime_depth)")
    ap.add_argument("--reports", type=Path, default=Path("reports"), help="its reports folder (default reports)")
    ap.add_argument("--first-seed", type=int, default=100, help="the first repetition's training seed, the next "
                    "ones following it (default 100)")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")


def open_study(args: argparse.Namespace) -> tuple[object, StudyContext]:
    """The study the options of :func:`add_study_options` name, and its context, with torch's threads set."""
    torch.set_num_threads(args.threads)
    study = load_study(args.study, None, args.reports)
    return study, study_context(study)


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


@dataclasses.dataclass(frozen=True)
class Retrained:
    """A network retrained and measured, as it ships (explorer.model.shipped: its exits no more accurate
    than an earlier path left out, unless the study keeps every exit): the candidate that ships, its paths'
    costs on the study's device for its first budget's kind and their errors, and what was left out."""

    candidate: Candidate
    costs: list[float]
    errors: list[float]
    dropped: tuple[DroppedExit, ...] = ()

    @property
    def loss_inputs(self) -> tuple[list[float], list[float]]:
        return self.costs, self.errors


def retrained(network: Network, recipe: DeploymentRecipe, seed: int, data: DeploymentData,
              context: StudyContext) -> Retrained:
    """``network`` trained from scratch with ``recipe`` and ``seed``, its paths measured on ``data``'s
    validation frames, and scored as it ships."""
    config, budget = context.config, context.budgets[0]
    costs = candidate_cost(network.candidate, tuple(config.input_size)).path_costs(context.device, budget.kind)
    weights = exit_loss_weights(costs, budget) if network.weights == "anytime" else None
    torch.manual_seed(seed)
    net = build_network(network.candidate)
    recipe = dataclasses.replace(recipe, train=dataclasses.replace(recipe.train, seed=seed, exit_weights=weights,
                                                                   self_distill=network.distill))
    result = train_for_deployment(net, data, recipe, torch.device("cpu"))
    shipped = ship(network.candidate, [float(x) for x in result.metrics[config.metric]], config.keep_every_exit)
    ships = candidate_cost(shipped.candidate, tuple(config.input_size)).path_costs(context.device, budget.kind)
    return Retrained(shipped.candidate, [float(c) for c in ships],
                     shipped.losses([float(x) for x in result.metrics[config.metric]]), shipped.dropped)


#: a path ready before this on the TX2 is an early one (the early-to-last ratio)
EARLY_MS = 9.0


def early_error(candidate: Candidate, errors: list[float], config: SearchConfig) -> float:
    """The mean error of ``candidate``'s paths (past the scan) ready before EARLY_MS on the TX2 (NaN where
    none is ready that early)."""
    ms = candidate_cost(candidate, tuple(config.input_size)).path_costs(get_device("tx2"), "time")
    early = [e for c, e in zip(ms[1:], errors[1:]) if c < EARLY_MS]
    return sum(early) / len(early) if early else float("nan")


def early_to_last(candidate: Candidate, errors: list[float], config: SearchConfig) -> float:
    """``early_error`` over the last path's error."""
    return early_error(candidate, errors, config) / errors[-1]


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
