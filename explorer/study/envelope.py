"""The envelope of dedicated networks: how good a study's winner is, not only against the paper design.

If the deadline were known in advance, one would run the best single-exit network of the space that is
ready by then. The anytime loss of that oracle (each budget served by the most accurate dedicated
network ready by it, the scan before the first) is what an anytime network of the same space and
recipe can approach: sharing one backbone among exits costs something, and the envelope says how much.

The dedicated networks come from every path of the search's candidates: for the last path, the
single-exit twin (the same network with its last exit only); for an earlier one (the LiDAR exit, an
encoder exit, an early decoder exit), the candidate trained with that path's loss alone, since the
space's networks all end in the decoder and only those earlier paths can answer early deadlines.
They are chosen along the cost range from the estimate (the front of estimated error against the
path's cost on the study's device, evenly spread along it), retrained with the finalists'
recipe at the deployment size (explorer.study.finalists) and stored as trials tagged ``envelope``
with the path they serve, so the work is cached and a killed run resumes; the study's single-exit
baselines that were retrained with the same recipe join them at no cost.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np
import optuna

from explorer.anytime import anytime_curve, anytime_loss
from explorer.cost import model_cost
from explorer.space import Candidate
from explorer.study.config import StudyContext
from explorer.study.finalists import FinalistJob, proxy_view, estimate_trials, finalist_trials, train_finalist
from explorer.study.objective import Objective
from explorer.study.planning import SAFETY
from explorer.study.records import record_values, trial_record
from explorer.study.results import trial_losses, trial_path_costs, winner
from explorer.study.storage import REPORTS_DIR, local_url, redacted, study_dir
from explorer.study.view import StudyView
from explorer.training.deployment import DeploymentRecipe

#: dedicated networks ``explorer envelope`` retrains unless told otherwise
DEFAULT_NETWORKS = 4

T = TypeVar("T")


def dedicated(candidate: Candidate) -> Candidate:
    """``candidate`` with its last exit only: the network one would run for one known deadline."""
    return dataclasses.replace(candidate, exits=(max(candidate.exits),), encoder_exits=(), lidar_exit=False)


@dataclasses.dataclass(frozen=True)
class DedicatedNetwork:
    """A network trained for one path alone: ``candidate`` trained with the loss of ``path`` only (its
    other exits untrained, and never run for that deadline). For a candidate's last path it is the
    single-exit twin (:func:`dedicated`); for an earlier one (the LiDAR exit, an encoder exit, an early
    decoder exit) the candidate itself, since the space's networks all end in the decoder."""

    candidate: Candidate
    path: int

    @property
    def key(self) -> str:
        return f"{self.candidate.key}/{self.path}"

    def recipe(self, base: DeploymentRecipe) -> DeploymentRecipe:
        """``base`` with the loss of this network's path alone (the same recipe for a single exit)."""
        exits = self.candidate.num_paths - 1
        if exits == 1:
            return base
        weights = tuple(1.0 if i == self.path - 1 else 0.0 for i in range(exits))
        return dataclasses.replace(base, train=dataclasses.replace(base.train, exit_weights=weights))


def dedicated_networks(candidate: Candidate) -> list[DedicatedNetwork]:
    """One dedicated network for each path of ``candidate`` (path 0, the scan, needs none)."""
    last = candidate.num_paths - 1
    return [DedicatedNetwork(candidate, p) for p in range(1, last)] + [DedicatedNetwork(dedicated(candidate), 1)]


def envelope_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if trial_record(t).is_envelope]


def dedicated_path(rec) -> int:
    """The path a retrained network of the envelope serves with, numbered as trained (the last one for a
    single exit)."""
    path = rec.envelope.path if rec.envelope is not None else None
    return path if path is not None else len(rec.path_metrics) - 1


def served_index(rec) -> int:
    """Where the path a network of the envelope serves with stands in its record's per-path figures, which
    are those of the network as it ships: its other exits, trained with no weight, are left out, and so
    is the dedicated exit where it is no more accurate than an earlier path, which then serves instead."""
    path = dedicated_path(rec)
    if rec.envelope is None or rec.shipped is None:
        return path
    kept = rec.shipped.trained_paths
    if path not in kept:
        path = next(int(d["better_path"]) for d in rec.shipped.dropped if int(d["path"]) == path)
    return kept.index(path)


def estimated_networks(study: optuna.Study, context: StudyContext) -> list[tuple[float, float, DedicatedNetwork]]:
    """Every dedicated network of the search's candidates that is ready within the budget's range, as
    (its path's cost on the device, its estimated error, the network), cheapest first; a network several
    trials share takes its best estimate. An early path's cost is the path's in its anytime network (the
    earlier exit heads included, a slight overestimate)."""
    config, device, budget = context.config, context.device, context.budget
    best: dict[str, tuple[float, float, DedicatedNetwork]] = {}
    for t in estimate_trials(study):
        rec = trial_record(t)
        if rec.baseline or rec.candidate is None:
            continue
        errors, costs = rec.losses_of(config.metric), trial_path_costs(t, device, budget.kind)
        for network in dedicated_networks(Candidate.from_dict(rec.shipped_candidate)):
            last = network.candidate.num_paths == 2
            error = errors[-1] if last else errors[network.path]
            if network.key not in best or error < best[network.key][1]:
                cost = (model_cost(network.candidate, config.input_size).path_costs(device, budget.kind)[-1]
                        if last else costs[network.path])
                best[network.key] = (cost, error, network)
    return sorted((p for p in best.values() if p[0] <= budget.upper), key=lambda p: (p[0], p[1]))


def spread_along_front(points: list[tuple[float, float, T]], count: int) -> list[T]:
    """``count`` of ``points`` (cost, estimated error, item) spread along the front of estimated error
    against cost: the point of the front nearest each of ``count`` evenly spaced costs from the cheapest
    to the front's end, cheapest first. Only a point on the front can serve some budget in an oracle
    (a cheaper one at least as accurate would serve it instead)."""
    front, lowest = [], math.inf
    for cost, error, item in sorted(points, key=lambda p: (p[0], p[1])):
        if error < lowest:
            lowest = error
            front.append((cost, item))
    if len(front) <= count:
        return [item for _, item in front]
    chosen: list[tuple[float, T]] = []
    for target in np.linspace(front[0][0], front[-1][0], count):
        chosen.append(min((p for p in front if all(p is not q for q in chosen)), key=lambda p: abs(p[0] - target)))
    return [item for _, item in sorted(chosen, key=lambda p: p[0])]


def choose_networks(study: optuna.Study, context: StudyContext, count: int) -> list[DedicatedNetwork]:
    """``count`` dedicated networks of every path of the search's candidates, spread over the budget's
    range by their estimate (:func:`spread_along_front`)."""
    return spread_along_front(estimated_networks(study, context), count)


def _winners_config(view: StudyView):
    """The study's settings with the finalists' steps the winner was retrained with: a time limit can
    shorten them after the study was created, and the envelope is trained and compared at the winner's."""
    config, best = view.config, winner(view.study)
    if best is not None and trial_record(best).is_retrained:
        return dataclasses.replace(config, finalist_steps=int(trial_record(best).finalist.recipe["steps"]))
    return config


def train_envelope(view: StudyView, count: int, reports: Path, deadline: float | None = None,
                   progress: Callable[[int, int, str], None] | None = None,
                   expected_s: float | None = None) -> list[optuna.trial.FrozenTrial]:
    """Retrains the chosen dedicated networks not yet retrained with the study's finalists' recipe (one at
    a time; with a ``deadline``, a network starts only if the longest so far says it ends before it, the
    first only if ``expected_s`` does, where given). The study gains trials: a reader after it takes a
    view made again."""
    study, context = view.study, view.context
    config = _winners_config(view)
    base = config.finalist_recipe()
    done = {f"{trial_record(t).candidate_key}/{dedicated_path(trial_record(t))}" for t in envelope_trials(study)
            if trial_record(t).envelope.recipe == base.to_dict()}
    todo = [n for n in choose_networks(study, context, count) if n.key not in done]
    if not todo:
        return envelope_trials(study)
    folder = study_dir(config.study, reports) / "envelope"
    objective = Objective(context.with_config(proxy_view(config)), study_dir(config.study, reports))
    took: list[float] = []
    for i, network in enumerate(todo):
        needs = SAFETY * max(took) if took else expected_s
        if deadline is not None and needs is not None and time.time() + needs > deadline:
            if progress:
                progress(i, len(todo), f"no time for the {len(todo) - i} other network(s): give a longer --time-limit")
            break
        if progress:
            progress(i, len(todo), f"training {network.candidate.key} for path {network.path}")
        started = time.time()
        result = train_finalist(objective, FinalistJob(network.candidate.to_dict()), recipe=network.recipe(base),
                                folder=folder / f"path{network.path}")
        took.append(time.time() - started)
        attrs = dict(result["user_attrs"])
        trained = attrs.pop("finalist")    # never a finalist: it cannot be the winner
        attrs.update(record_values(envelope={**trained, "recipe": base.to_dict(), "path": network.path}))
        study.add_trial(optuna.trial.create_trial(values=result["values"], user_attrs=attrs,
                                                  state=optuna.trial.TrialState.COMPLETE))
        Path(result["checkpoint"]).unlink(missing_ok=True)
    if progress:
        progress(len(todo), len(todo), "dedicated networks retrained")
    return envelope_trials(study)


def envelope_members(view: StudyView) -> list[optuna.trial.FrozenTrial]:
    """The dedicated networks of the envelope: those retrained for it and the single-exit baselines
    retrained with the same recipe."""
    recipe = _winners_config(view).finalist_recipe().to_dict()
    mine = [t for t in envelope_trials(view.study) if trial_record(t).envelope.recipe == recipe]
    single = [t for t in finalist_trials(view.study) if _single_exit_baseline(trial_record(t), recipe)]
    return mine + single


def _single_exit_baseline(rec, recipe: dict) -> bool:
    return bool(rec.baseline and rec.candidate is not None and len(rec.path_metrics) == 2
                and rec.finalist.recipe == recipe)


def envelope_steps(scan_error: float, points: list[tuple[float, float]]) -> tuple[list[float], list[float]]:
    """The oracle's steps (costs, errors) from the scan on (cost 0, ``scan_error``), given each dedicated
    network's (cost, error): a budget is served by the most accurate network ready by it, so a network
    no better than a cheaper one (or than the scan) serves none and is left out."""
    costs, errors = [0.0], [scan_error]
    for cost, error in sorted(points):
        if error < errors[-1]:
            costs.append(cost)
            errors.append(error)
    return costs, errors


@dataclasses.dataclass(frozen=True)
class Envelope:
    """The oracle's steps (cost, error) from the scan on, its anytime loss, the winner's, and which
    networks make it."""

    costs: list[float]
    errors: list[float]
    loss: float
    winner_loss: float | None
    networks: list[dict]
    unit: str = "ms"

    @property
    def ratio(self) -> float | None:
        return self.winner_loss / self.loss if self.winner_loss is not None and self.loss > 0 else None

    @property
    def below_one(self) -> str | None:
        """Why the winner can beat the oracle, where it does: the oracle has only its few networks, so
        before the first only the scan serves it, and between them (or after the last) the winner's
        exits can be more accurate."""
        if self.ratio is None or self.ratio >= 1 or len(self.costs) < 2:
            return None
        ready = ", ".join(f"{c:.1f}" for c in self.costs[1:])
        return (f"below 1 where the winner's exits are more accurate than the envelope's network for that "
                f"deadline: its networks are ready at {ready} {self.unit}, only the scan before the first; more "
                "dedicated networks (explorer envelope --networks) close the gaps")

    def curve(self, upper: float) -> tuple[np.ndarray, np.ndarray]:
        return anytime_curve(self.costs, self.errors, upper)


def envelope(view: StudyView) -> Envelope | None:
    """The envelope of the study's dedicated networks on its device and first budget (None before any
    is retrained). Each budget is served by the most accurate network ready by it; before the first,
    by the scan (path 0, as the winner measured it)."""
    config, device, budget = view.config, view.context.device, view.context.budget
    members = envelope_members(view)
    best = winner(view.study)
    if not members or best is None:
        return None
    points = sorted(((trial_path_costs(t, device, budget.kind)[served_index(trial_record(t))],
                      trial_losses(t, config.metric)[served_index(trial_record(t))], t)
                     for t in members), key=lambda p: (p[0], p[1]))
    costs, errors = envelope_steps(trial_losses(best, config.metric)[0], [(c, e) for c, e, _ in points])
    networks = [{"number": t.number, "candidate_key": trial_record(t).candidate_key,
                 "path": dedicated_path(trial_record(t)), "baseline": trial_record(t).baseline or "",
                 "cost": cost, config.metric: error}
                for cost, error, t in points]
    return Envelope(costs, errors, anytime_loss(costs, errors, budget),
                    best.values[0] if trial_record(best).is_retrained else None, networks, budget.unit)


def envelope_command(study: str, storage_url: str | None = None, reports: Path | None = None) -> str:
    """The ``explorer envelope`` command for ``study``: with ``--storage`` where the study is not in its
    journal on this machine (a PostgreSQL database, a journal elsewhere; the password hidden), with
    ``--reports`` where that is not the default folder."""
    command = f"explorer envelope --study {study}"
    if reports is not None and Path(reports) != REPORTS_DIR:
        command += f" --reports {reports}"
    if storage_url and storage_url != local_url(study, reports if reports is not None else REPORTS_DIR):
        command += f" --storage {redacted(storage_url)}"
    return command


def envelope_hint(view: StudyView, storage_url: str | None = None, reports: Path | None = None) -> str | None:
    """How to compute the envelope, when the winner is retrained and no dedicated network of the space
    is yet (the single-exit baselines alone may make one); None otherwise. ``storage_url`` and
    ``reports``: where the study is, for the command (:func:`envelope_command`)."""
    best = winner(view.study)
    recipe = _winners_config(view).finalist_recipe().to_dict()
    if best is None or not trial_record(best).is_retrained or any(
            trial_record(t).envelope.recipe == recipe for t in envelope_trials(view.study)):
        return None
    return (f"`{envelope_command(view.config.study, storage_url, reports)}` retrains {DEFAULT_NETWORKS} "
            f"networks of the space, each trained for one path, with the finalists' recipe (about as long as "
            f"{DEFAULT_NETWORKS} finalists) and says how close the winner comes to the best network for each "
            "deadline known in advance")


def envelope_summary(view: StudyView, storage_url: str | None = None, reports: Path | None = None) -> str | None:
    """The summary's sentence on the envelope: its anytime loss and the winner's ratio to it, what it is
    made of, and how to compute it where no dedicated network of the space is yet (None when there is
    nothing to say: no retrained winner). ``storage_url``, ``reports``: as :func:`envelope_hint`."""
    found, hint = envelope(view), envelope_hint(view, storage_url, reports)
    parts = []
    if found is not None and found.ratio is not None:
        parts.append(f"the winner's anytime loss is {found.ratio:.3f} x the envelope of {len(found.networks)} "
                     f"dedicated networks ({found.loss:.4f}: each deadline served by the best network trained for "
                     f"it alone and ready by it{', here the single-exit baselines only' if hint else ''})")
        if found.below_one:
            parts.append(found.below_one)
    if hint:
        parts.append(hint if parts else f"no envelope of dedicated networks yet: {hint}")
    return "; ".join(parts) or None
