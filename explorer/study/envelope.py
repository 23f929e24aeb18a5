"""The envelope of dedicated networks: how good a study's winner is, not only against the paper design.

If the deadline were known in advance, one would run the best single-exit network of the space that is
ready by then. The anytime loss of that oracle (each budget served by the most accurate dedicated
network ready by it, the scan before the first) is what an anytime network of the same space and
recipe can approach: sharing one backbone among exits costs something, and the envelope says how much.

The dedicated networks are the single-exit twins of the search's candidates (the same network with its
last exit only), chosen along the cost range from the estimate: the front of estimated last-path error
against the twin's cost on the study's device, spread over the budget's range. They are retrained with
the finalists' recipe at the deployment size (explorer.study.finalists) and stored as trials tagged
``envelope``, so the work is cached and a killed run resumes; the study's single-exit baselines that
were retrained with the same recipe join them at no cost.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np
import optuna

from explorer.anytime import anytime_curve, anytime_loss
from explorer.cost import model_cost
from explorer.space import Candidate
from explorer.study._finalist_pool import InProcess
from explorer.study.config import StudyContext, study_config, study_context
from explorer.study.finalists import FinalistJob, proxy_view, estimate_trials, finalist_trials, train_finalist
from explorer.study.objective import Objective
from explorer.study.planning import SAFETY
from explorer.study.records import record_values, trial_record
from explorer.study.results import winner
from explorer.study.storage import study_dir

#: dedicated networks ``explorer envelope`` retrains unless told otherwise
DEFAULT_NETWORKS = 4


def dedicated(candidate: Candidate) -> Candidate:
    """``candidate`` with its last exit only: the network one would run for one known deadline."""
    return dataclasses.replace(candidate, exits=(max(candidate.exits),), encoder_exits=(), lidar_exit=False)


def envelope_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if trial_record(t).is_envelope]


def choose_networks(study: optuna.Study, context: StudyContext, count: int) -> list[Candidate]:
    """``count`` dedicated networks spread over the budget's range: the single-exit twins of the search's
    candidates on the front of estimated last-path error against their last path's cost on the device,
    the one nearest each of ``count`` evenly spaced costs up to the budget's upper end."""
    config, device, budget = context.config, context.device, context.budget
    best: dict[str, tuple[float, float, Candidate]] = {}
    for t in estimate_trials(study):
        rec = trial_record(t)
        if rec.baseline or rec.candidate is None:
            continue
        twin = dedicated(Candidate.from_dict(rec.candidate))
        error = rec.losses_of(config.metric)[-1]
        if twin.key not in best or error < best[twin.key][1]:
            cost = model_cost(twin, config.input_size).path_costs(device, budget.kind)[-1]
            best[twin.key] = (cost, error, twin)
    front, lowest = [], math.inf
    for cost, error, twin in sorted(best.values(), key=lambda x: x[0]):
        if error < lowest and cost <= budget.upper:
            lowest = error
            front.append((cost, twin))
    if len(front) <= count:
        return [twin for _, twin in front]
    targets = np.linspace(front[0][0], front[-1][0], count)
    chosen: list[Candidate] = []
    for target in targets:
        nearest = min((pair for pair in front if pair[1] not in chosen), key=lambda p: abs(p[0] - target))
        chosen.append(nearest[1])
    return chosen


def train_envelope(study: optuna.Study, count: int, reports: Path, deadline: float | None = None,
                   progress: Callable[[int, int, str], None] | None = None) -> list[optuna.trial.FrozenTrial]:
    """Retrains the chosen dedicated networks not yet retrained with the study's finalists' recipe (one at
    a time; with a ``deadline``, a network starts only if the longest so far says it ends before it)."""
    context = study_context(study)
    config = context.config
    recipe = config.finalist_recipe()
    done = {trial_record(t).candidate_key for t in envelope_trials(study)
            if trial_record(t).envelope.recipe == recipe.to_dict()}
    todo = [c for c in choose_networks(study, context, count) if c.key not in done]
    if not todo:
        return envelope_trials(study)
    folder = study_dir(config.study, reports) / "envelope"
    runner = InProcess(functools.partial(Objective, context.with_config(proxy_view(config)),
                                         study_dir(config.study, reports)),
                       functools.partial(train_finalist, recipe=recipe, folder=folder))
    took: list[float] = []
    for i, candidate in enumerate(todo):
        if deadline is not None and took and time.time() + SAFETY * max(took) > deadline:
            if progress:
                progress(i, len(todo), f"no time for the {len(todo) - i} other network(s): give a longer --time-limit")
            break
        if progress:
            progress(i, len(todo), f"training {candidate.key} ({candidate.describe()[:60]})")
        started = time.time()
        result = runner.submit(FinalistJob(candidate.to_dict())).result()
        took.append(time.time() - started)
        attrs = dict(result["user_attrs"])
        attrs.update(record_values(envelope=attrs.pop("finalist")))   # never a finalist: it cannot be the winner
        study.add_trial(optuna.trial.create_trial(values=result["values"], user_attrs=attrs,
                                                  state=optuna.trial.TrialState.COMPLETE))
        Path(result["checkpoint"]).unlink(missing_ok=True)
    if progress:
        progress(len(todo), len(todo), "dedicated networks retrained")
    return envelope_trials(study)


def envelope_members(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    """The dedicated networks of the envelope: those retrained for it and the single-exit baselines
    retrained with the same recipe."""
    recipe = study_config(study).finalist_recipe().to_dict()
    mine = [t for t in envelope_trials(study) if trial_record(t).envelope.recipe == recipe]
    single = [t for t in finalist_trials(study) if _single_exit_baseline(trial_record(t), recipe)]
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
        """Why the winner can beat the oracle, where it does: the dedicated networks all end in the
        decoder, so early deadlines have only the scan."""
        if self.ratio is None or self.ratio >= 1 or len(self.costs) < 2:
            return None
        return (f"below 1 where the winner's early exits answer before the cheapest dedicated network is ready "
                f"({self.costs[1]:.1f} {self.unit}): every dedicated network ends in the decoder, and until then "
                "the oracle has only the scan")

    def curve(self, upper: float) -> tuple[np.ndarray, np.ndarray]:
        return anytime_curve(self.costs, self.errors, upper)


def envelope(study: optuna.Study) -> Envelope | None:
    """The envelope of the study's dedicated networks on its device and first budget (None before any
    is retrained). Each budget is served by the most accurate network ready by it; before the first,
    by the scan (path 0, as the winner measured it)."""
    from explorer.study.results import trial_losses, trial_path_costs
    context = study_context(study)
    config, device, budget = context.config, context.device, context.budget
    members = envelope_members(study)
    best = winner(study)
    if not members or best is None:
        return None
    points = sorted(((trial_path_costs(t, device, budget.kind)[-1], trial_losses(t, config.metric)[-1], t)
                     for t in members), key=lambda p: (p[0], p[1]))
    costs, errors = envelope_steps(trial_losses(best, config.metric)[0], [(c, e) for c, e, _ in points])
    networks = [{"number": t.number, "candidate_key": trial_record(t).candidate_key,
                 "baseline": trial_record(t).baseline or "", "cost": cost, config.metric: error}
                for cost, error, t in points]
    return Envelope(costs, errors, anytime_loss(costs, errors, budget),
                    best.values[0] if trial_record(best).is_retrained else None, networks, budget.unit)


def envelope_hint(study: optuna.Study) -> str | None:
    """How to compute the envelope, when the winner is retrained and no dedicated network of the space
    is yet (the single-exit baselines alone may make one); None otherwise."""
    best = winner(study)
    recipe = study_config(study).finalist_recipe().to_dict()
    if best is None or not trial_record(best).is_retrained or any(
            trial_record(t).envelope.recipe == recipe for t in envelope_trials(study)):
        return None
    return (f"`explorer envelope --study {study_config(study).study}` retrains {DEFAULT_NETWORKS} single-exit "
            f"networks of the space with the finalists' recipe (about as long as {DEFAULT_NETWORKS} finalists) "
            "and says how close the winner comes to the best network for each deadline known in advance")


def envelope_summary(study: optuna.Study) -> str | None:
    """The summary's sentence on the envelope: its anytime loss and the winner's ratio to it, what it is
    made of, and how to compute it where no dedicated network of the space is yet (None when there is
    nothing to say: no retrained winner)."""
    found, hint = envelope(study), envelope_hint(study)
    parts = []
    if found is not None and found.ratio is not None:
        parts.append(f"the winner's anytime loss is {found.ratio:.3f} x the envelope of {len(found.networks)} "
                     f"dedicated networks ({found.loss:.4f}: each deadline served by the best single-exit network "
                     f"ready by it{', here the single-exit baselines only' if hint else ''})")
        if found.below_one:
            parts.append(found.below_one)
    if hint:
        parts.append(hint if parts else f"no envelope of dedicated networks yet: {hint}")
    return "; ".join(parts) or None
