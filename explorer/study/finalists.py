"""The end of a study: its best distinct candidates and the baselines, retrained stand-alone with one
longer recipe, so that the winner and its ratio to the paper design are measured, not estimated.

Each retraining is stored as a trial of its own (no sampled parameters, so samplers ignore it)
tagged ``finalist`` with the estimate it is compared to. A retraining checkpoints as it goes: a
killed study resumes it where it stopped; a finished one is never redone.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

import optuna

from explorer.model import build_model
from explorer.space import Candidate
from explorer.study.config import baseline_model, json_safe
from explorer.study.objective import Objective
from explorer.study.planning import SAFETY
from explorer.study.storage import study_dir
from explorer.training.train import train

FINALIST = "finalist"


def is_finalist(trial: optuna.trial.FrozenTrial) -> bool:
    return FINALIST in trial.user_attrs


def estimate_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    """Completed search trials with metrics (finalists' retrainings excluded)."""
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if "path_metrics" in t.user_attrs and "workloads" in t.user_attrs and not is_finalist(t)]


def finalist_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if is_finalist(t)]


def _encoder(trial: optuna.trial.FrozenTrial) -> tuple:
    c = trial.user_attrs["candidate"]
    return c.get("encoder_blocks"), c.get("width_mult")


def choose_finalists(study: optuna.Study, count: int) -> list[optuna.trial.FrozenTrial]:
    """The ``count`` best distinct candidates of the search (baselines aside), spread over image
    encoders: the best estimate, then the best estimate of each other encoder (depth, width) in
    order, then the next best candidates whatever their encoder.

    The supernet's error depends on the encoder's size: it ranks larger encoders above smaller ones
    that retrain better (measured on the default space: 9, 7 and 6 blocks at x1 estimated in that
    order, retrained in the reverse one), so the best few estimates, near-copies of one network,
    would all carry the same error. One finalist per encoder lets retraining decide between sizes.
    """
    ranked, seen = [], set()
    for t in sorted(estimate_trials(study), key=lambda t: t.values[0]):
        key = t.user_attrs["candidate_key"]
        if not t.user_attrs.get("baseline") and key not in seen:
            seen.add(key)
            ranked.append(t)
    chosen, encoders = [], set()
    for t in ranked:
        if len(chosen) < count and _encoder(t) not in encoders:
            encoders.add(_encoder(t))
            chosen.append(t)
    numbers = {t.number for t in chosen}
    chosen += [t for t in ranked if t.number not in numbers][:max(count - len(chosen), 0)]
    return chosen


def retrain_finalists(study: optuna.Study, config, reports: Path,
                      progress: Callable[[int, int, str], None] | None = None, extra: int = 0,
                      deadline: float | None = None) -> list[optuna.trial.FrozenTrial]:
    """Retrains the finalists and the baselines (those not retrained yet with this recipe), then up to
    ``extra`` more finalists. With a ``deadline`` (a time.time()), the best finalist and the paper
    design are retrained whatever the time; every other job only if it should end before the deadline,
    judged by how long the jobs took here (a machine that slowed after planning drops the last
    finalists and baselines rather than overrun; one that turned out faster gets the extras)."""
    recipe = config.finalist_config()
    chosen = choose_finalists(study, config.finalists + max(extra, 0))
    finalists = [(Candidate.from_dict(t.user_attrs["candidate"]), "", t) for t in chosen[:config.finalists]]
    baselines = []
    if config.baselines:
        estimated = {t.user_attrs.get("baseline"): t for t in estimate_trials(study) if t.user_attrs.get("baseline")}
        baselines = [(baseline_model(name), name, estimated.get(name)) for name in config.baselines]
    optional = [(Candidate.from_dict(t.user_attrs["candidate"]), "", t) for t in chosen[config.finalists:]]
    # what a study cannot do without (its best finalist, the paper design to compare it with) first
    must = finalists[:1] + [b for b in baselines if b[1] == "paper"]
    must_ids = {id(j) for j in must}
    jobs = must + [j for j in finalists + baselines if id(j) not in must_ids] + optional
    done = {(t.user_attrs["candidate_key"], t.user_attrs.get("baseline", "")) for t in finalist_trials(study)
            if t.user_attrs[FINALIST].get("recipe") == recipe.to_dict()}
    todo = [j for j in jobs if (j[0].key, j[1]) not in done]
    if not todo:
        return finalist_trials(study)
    objective = Objective(_proxy_view(config), study_dir(config.study, reports))
    folder = study_dir(config.study, reports) / "finalists"
    took: list[float] = []      # seconds of each job retrained here
    for i, job in enumerate(todo):
        candidate, baseline, estimate = job
        label = baseline or f"trial {estimate.number}"
        if deadline is not None and id(job) not in must_ids:
            expected = SAFETY * max(took) if took else math.inf
            if time.time() + expected > deadline:
                if progress:
                    progress(i, i, f"no time for {label} ({candidate.key}) or the jobs after it: about {expected:.0f} s each")
                break
        if progress:
            progress(i, len(todo), f"retraining {label} ({candidate.key})")
        start = time.time()
        _retrain(study, objective, candidate, baseline, estimate, recipe, folder)
        took.append(time.time() - start)
    if progress:
        progress(len(todo), len(todo), "finalists retrained")
    return finalist_trials(study)


def _proxy_view(config):
    """The study's settings with the proxy evaluator: a finalist is trained, never sliced."""
    import dataclasses
    return dataclasses.replace(config, evaluator="proxy", pruning=False)


def _retrain(study: optuna.Study, objective, candidate: Candidate, baseline: str,
             estimate: optuna.trial.FrozenTrial | None, recipe, folder: Path) -> None:
    import torch
    folder.mkdir(parents=True, exist_ok=True)
    checkpoint = folder / f"{candidate.key}.pt"     # a kill resumes from here
    holder = optuna.trial.FixedTrial({})           # collects user attrs like a live trial
    cost, pm, latency = objective.describe(holder, candidate)
    torch.manual_seed(recipe.seed)
    net = build_model(candidate)
    result = train(net, objective.train_set, objective.val_set, recipe, objective.torch_device,
                   checkpoint=checkpoint, val_limit=objective.config.val_limit)
    path_metrics = json_safe(result.metrics.drop(columns=["path"]).to_dict("records"))
    if candidate.precision == "int8":
        path_metrics = objective.quantized(holder, net, path_metrics, cost)
    path_losses = [m[objective.config.metric] for m in path_metrics]
    if any(not math.isfinite(v) for v in path_losses):
        checkpoint.unlink(missing_ok=True)
        raise FloatingPointError(f"finalist {candidate.key}: non-finite validation loss {path_losses}")
    losses = objective.losses_for(cost, path_losses)
    values = objective.values(losses, pm, latency)
    attrs = dict(holder.user_attrs)
    attrs.update({"path_metrics": path_metrics, "losses": losses,
                  "train": {"seconds": result.seconds, "steps": result.steps,
                            "images_per_second": result.images_per_second},
                  "evaluator": {"evaluator": "retrained", "steps": recipe.steps},
                  FINALIST: {"estimate_trial": estimate.number if estimate else None,
                             "estimated": estimate.values[0] if estimate else None,
                             "recipe": recipe.to_dict()}})
    if baseline:
        attrs["baseline"] = baseline
    if objective.artifacts is not None:
        attrs["weights_artifact"] = optuna.artifacts.upload_artifact(
            artifact_store=objective.artifacts, file_path=str(checkpoint), study_or_trial=study)
    study.add_trial(optuna.trial.create_trial(values=list(values) if isinstance(values, tuple) else [values],
                                              user_attrs=attrs, state=optuna.trial.TrialState.COMPLETE))
    checkpoint.unlink(missing_ok=True)
