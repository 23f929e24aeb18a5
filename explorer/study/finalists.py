"""The end of a study: its best distinct candidates and the baselines, retrained stand-alone with one
longer recipe, so that the winner and its ratio to the paper design are measured, not estimated.

Each retraining is stored as a trial of its own (no sampled parameters, so samplers ignore it)
tagged ``finalist`` with the estimate it is compared to. A retraining checkpoints as it goes: a
killed study resumes it where it stopped; a finished one is never redone. With several GPUs, or
``workers`` processes on a CPU, the finalists retrain at the same time (:mod:`._finalist_pool`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import optuna

from explorer.model import build_model
from explorer.space import Candidate
from explorer.study._finalist_pool import InProcess, WorkerPool, finalist_devices
from explorer.study.config import StudyContext, baseline_model, json_safe
from explorer.study.objective import Objective
from explorer.study.planning import SAFETY
from explorer.study.records import Measured, Retraining, record_values, trial_record
from explorer.study.storage import study_dir
from explorer.training.deployment import DeploymentRecipe, train_for_deployment
from explorer.training.train import evaluated_frames



def is_finalist(trial: optuna.trial.FrozenTrial) -> bool:
    return trial_record(trial).is_retrained


def estimate_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    """Completed search trials with metrics (finalists' retrainings excluded)."""
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if trial_record(t).is_estimate]


def finalist_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if is_finalist(t)]


def _encoder(trial: optuna.trial.FrozenTrial) -> tuple:
    c = trial_record(trial).candidate
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
        key = trial_record(t).candidate_key
        if not trial_record(t).baseline and key not in seen:
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


@dataclass(frozen=True)
class FinalistJob:
    """One retraining: a candidate of the search (``candidate``, its estimate trial) or a baseline
    (by name). ``must``: retrained whatever the time; ``optional``: beyond the plan, only if time is left."""

    candidate: dict | None
    baseline: str = ""
    estimate_number: int | None = None
    estimated: float | None = None
    must: bool = False
    optional: bool = False

    def model(self):
        return baseline_model(self.baseline) if self.baseline else Candidate.from_dict(self.candidate)

    @property
    def label(self) -> str:
        return self.baseline or f"trial {self.estimate_number}"


def _job(trial: optuna.trial.FrozenTrial | None, baseline: str = "", **flags) -> FinalistJob:
    return FinalistJob(None if baseline else trial_record(trial).candidate, baseline,
                       trial.number if trial else None, trial.values[0] if trial else None, **flags)


def finalist_jobs(study: optuna.Study, config, extra: int = 0) -> list[FinalistJob]:
    """The retrainings still to do, in order: the best finalist and the paper design first (what a study
    cannot do without), then the other finalists and baselines, then up to ``extra`` more finalists."""
    chosen = choose_finalists(study, config.finalists + max(extra, 0))
    finalists = [_job(t) for t in chosen[:config.finalists]]
    baselines = []
    if config.baselines:
        estimated = {trial_record(t).baseline: t for t in estimate_trials(study) if trial_record(t).baseline}
        baselines = [_job(estimated.get(name), name) for name in config.baselines]
    must = finalists[:1] + [j for j in baselines if j.baseline == "paper"]
    rest = finalists[1:] + [j for j in baselines if j.baseline != "paper"]
    jobs = [dataclasses.replace(j, must=True) for j in must] + rest + \
        [dataclasses.replace(_job(t), optional=True) for t in chosen[config.finalists:]]
    recipe = config.finalist_recipe().to_dict()
    done = {(trial_record(t).candidate_key, trial_record(t).baseline or "") for t in finalist_trials(study)
            if trial_record(t).finalist.recipe == recipe}
    return [j for j in jobs if (j.model().key, j.baseline) not in done]


def retrain_finalists(study: optuna.Study, context: StudyContext, reports: Path,
                      progress: Callable[[int, int, str], None] | None = None, extra: int = 0,
                      deadline: float | None = None, workers: int = 1) -> list[optuna.trial.FrozenTrial]:
    """Retrains the finalists and the baselines (those not retrained yet with this recipe), then up to
    ``extra`` more finalists. With a ``deadline`` (a time.time()), the best finalist and the paper
    design are retrained whatever the time; every other job only if it should end before the deadline,
    judged by how long the jobs took here (a machine that slowed after planning drops the last
    finalists and baselines rather than overrun; one that turned out faster gets the extras).
    ``workers``: processes retraining at once on a CPU; a machine with several GPUs retrains one
    finalist per GPU, a machine with one GPU one after another (see ``finalist_devices``)."""
    config = context.config
    todo = finalist_jobs(study, config, extra)
    if not todo:
        return finalist_trials(study)
    make_objective = functools.partial(Objective, context.with_config(proxy_view(config)),
                                       study_dir(config.study, reports))
    run_job = functools.partial(train_finalist, recipe=config.finalist_recipe(),
                                folder=study_dir(config.study, reports) / "finalists")
    devices = finalist_devices(config.accelerator, workers)[:len(todo)]
    runner = WorkerPool(devices, make_objective, run_job) if len(devices) > 1 else InProcess(make_objective, run_job)
    artifacts = None
    if config.keep_weights:
        from optuna.artifacts import FileSystemArtifactStore
        (study_dir(config.study, reports) / "artifacts").mkdir(parents=True, exist_ok=True)
        artifacts = FileSystemArtifactStore(str(study_dir(config.study, reports) / "artifacts"))
    with runner:
        _dispatch(todo, runner, len(devices), deadline, progress, lambda result: _store(study, artifacts, result))
    if progress:
        progress(len(todo), len(todo), "finalists retrained")
    return finalist_trials(study)


def _dispatch(todo: list[FinalistJob], runner, slots: int, deadline: float | None,
              progress: Callable[[int, int, str], None] | None, store: Callable[[dict], None]) -> None:
    """Keeps ``slots`` jobs running, in order, storing each result as it comes. A job that is not a
    must starts only if, by the longest job so far, it ends before ``deadline``; an optional one not
    before a job has been timed."""
    queue, running, took, started = list(todo), {}, [], 0
    while queue or running:
        while queue and len(running) < slots:
            job = queue[0]
            if deadline is not None and not job.must and (took or job.optional):
                expected = SAFETY * max(took) if took else math.inf
                if time.time() + expected > deadline:
                    if progress:
                        progress(started, started, f"no time for {job.label} ({job.model().key}) or the jobs "
                                 f"after it: about {expected:.0f} s each")
                    queue = []
                    break
            queue.pop(0)
            if progress:
                progress(started, len(todo), f"retraining {job.label} ({job.model().key})")
            running[runner.submit(job)] = time.time()
            started += 1
        if not running:
            break
        finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
        for future in finished:
            took.append(time.time() - running.pop(future))
            store(future.result())


def proxy_view(config):
    """The study's settings with the proxy evaluator: a finalist is trained, never sliced."""
    return dataclasses.replace(config, evaluator="proxy", pruning=False)


def train_finalist(objective, job: FinalistJob, recipe: DeploymentRecipe, folder: Path) -> dict:
    """Trains ``job``'s network with ``recipe`` (resuming its checkpoint in ``folder``), measures every path
    at the deployment size, and returns what its trial stores: ``values``, ``user_attrs`` and the
    ``checkpoint`` with the weights. Runs in this process or in a worker; the study itself is written by
    the caller."""
    import torch
    folder.mkdir(parents=True, exist_ok=True)
    candidate = job.model()
    checkpoint = folder / f"{candidate.key}.pt"     # a kill resumes from here
    holder = optuna.trial.FixedTrial({})           # collects user attrs like a live trial
    cost, pm, latency = objective.describe(holder, candidate)
    torch.manual_seed(recipe.train.seed)
    net = build_model(candidate)
    data = objective.deployment_data()
    result = train_for_deployment(net, data, recipe, objective.torch_device, checkpoint=checkpoint,
                                  val_limit=objective.config.val_limit)
    path_metrics = json_safe(result.metrics.drop(columns=["path"]).to_dict("records"))
    if candidate.precision == "int8":
        path_metrics = objective.quantized(holder, net, path_metrics, cost, recipe.deploy_size)
    path_losses = [m[objective.config.metric] for m in path_metrics]
    if any(not math.isfinite(v) for v in path_losses):
        checkpoint.unlink(missing_ok=True)
        raise FloatingPointError(f"finalist {candidate.key}: non-finite validation loss {path_losses}")
    (cost, pm, latency), path_metrics = objective.shipped(holder, candidate, (cost, pm, latency), path_metrics)
    path_losses = [m[objective.config.metric] for m in path_metrics]
    losses = objective.losses_for(cost, path_losses)
    values = objective.values(losses, pm, latency)
    attrs = {**holder.user_attrs, **record_values(
        path_metrics=path_metrics, losses=losses,
        measured=measurement(objective.config, data.deploy_val, recipe.deploy_size),
        train={"seconds": result.seconds, "steps": result.steps, "images_per_second": result.images_per_second,
               "device": str(objective.torch_device)},
        evaluator={"evaluator": "retrained", "steps": recipe.train.steps,
                   "tune_steps": recipe.tune_steps if recipe.tunes else 0},
        finalist=Retraining(estimate_trial=job.estimate_number, estimated=job.estimated, recipe=recipe.to_dict()),
        baseline=job.baseline or None)}
    return {"values": list(values) if isinstance(values, tuple) else [values], "user_attrs": attrs,
            "checkpoint": str(checkpoint)}


def measurement(config, val_set, size: tuple[int, int]) -> Measured:
    """Where a retrained network's per-path figures come from: which frames, at which size."""
    return Measured(data=config.data, split="val", frames=evaluated_frames(val_set, config.val_limit),
                    input_size=tuple(size))


def _store(study: optuna.Study, artifacts, result: dict) -> None:
    """One retrained finalist as a trial of ``study``, its weights as an artifact; the checkpoint goes."""
    attrs, checkpoint = dict(result["user_attrs"]), Path(result["checkpoint"])
    if artifacts is not None:
        attrs.update(record_values(weights_artifact=optuna.artifacts.upload_artifact(
            artifact_store=artifacts, file_path=str(checkpoint), study_or_trial=study)))
    study.add_trial(optuna.trial.create_trial(values=result["values"], user_attrs=attrs,
                                              state=optuna.trial.TrialState.COMPLETE))
    checkpoint.unlink(missing_ok=True)
