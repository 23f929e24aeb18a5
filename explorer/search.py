"""The search: Optuna over a search space, minimising the anytime loss on a device.

Each trial samples a candidate, costs its paths on the device (no training), rejects it if a
constraint rules it out, trains it with the proxy recipe (reporting the anytime loss so hopeless
ones are pruned), and stores everything re-scoring needs. The paper's design, the same without
early exits, and a FastDepth-like network are the study's first trials, tagged as baselines.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import optuna

from explorer import __version__
from explorer.anytime import anytime_loss, parse_budget
from explorer.cost import candidate_cost, get_device
from explorer.errors import UserError
from explorer.results import compact_workloads
from explorer.space import (Candidate, SearchSpace, fastdepth_candidate, paper_candidate,
                            paper_nee_candidate)
from explorer.storage import REPORTS_DIR, fail_interrupted_trials, open_storage, study_dir
from explorer.train import PROXY, Pruned, TrainConfig, resolve_device, train

BASELINES: dict[str, Callable[[], Candidate]] = {
    "paper": paper_candidate, "paper-nee": paper_nee_candidate, "fastdepth": fastdepth_candidate}
OBJECTIVES = ("anytime_loss", "params", "macs", "first_exit_ms")


@dataclass(frozen=True)
class SearchConfig:
    study: str
    space: str = "anytime_depth"
    device: str = "tx2"
    budgets: tuple[str, ...] = ("time:uniform:33ms",)
    data: str = "synthetic"
    objectives: tuple[str, ...] = ("anytime_loss",)
    metric: str = "rmse"
    input_size: tuple[int, int] = (224, 224)     # deployment size: costs are computed here
    train_size: tuple[int, int] = (64, 64)       # proxy training resolution
    train_steps: int = 150
    batch_size: int = 16
    lr: float = PROXY.lr
    val_limit: int | None = 96
    seed: int = 0
    max_params: float | None = None
    max_first_exit_ms: float | None = None
    baselines: bool = True
    pruning: bool = True
    keep_weights: bool = True
    accelerator: str = "auto"
    supervision: str = "supervised"              # supervised | self | mixed (see explorer.selfsup)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("budgets", "objectives", "input_size", "train_size"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SearchConfig":
        d = dict(d)
        for k in ("budgets", "objectives", "input_size", "train_size"):
            d[k] = tuple(d[k])
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def train_config(self) -> TrainConfig:
        return dataclasses.replace(PROXY, steps=self.train_steps, batch_size=self.batch_size,
                                   input_size=self.train_size, lr=self.lr, lr_end=self.lr / 10,
                                   seed=self.seed, supervision=self.supervision,
                                   eval_every=max(2 * self.train_steps // 3, 1) if self.pruning else 0)

    def validate(self) -> None:
        SearchSpace.from_yaml(self.space)
        get_device(self.device)
        if not self.budgets:
            raise UserError("give at least one --budget")
        for b in self.budgets:
            parse_budget(b)
        bad = [o for o in self.objectives if o not in OBJECTIVES]
        if bad or not self.objectives or self.objectives[0] != "anytime_loss":
            raise UserError(f"--objectives must start with anytime_loss and use only {list(OBJECTIVES)}")
        if self.metric not in ("rmse", "mae", "rel"):
            raise UserError(f"--metric {self.metric}: use rmse, mae or rel")
        for name, size in (("--input-size", self.input_size), ("--train-size", self.train_size)):
            if len(size) != 2 or min(size) < 8:
                raise UserError(f"{name} {size}: give HxW, e.g. 224x224")
        if self.train_steps < 1:
            raise UserError("--train-steps must be at least 1")
        self.train_config().validate()
        from explorer.data import parse_data_spec
        if self.supervision != "supervised" and not parse_data_spec(self.data).is_sequence:
            raise UserError(f"--supervision {self.supervision} needs sequence data (--data synthetic-seq, "
                            "kitti-seq:DRIVE or frames:FOLDER)")

    # settings that change what a trial's value means: a resumed study must keep them
    IDENTITY = ("space", "device", "budgets", "data", "objectives", "metric", "input_size", "train_size",
                "train_steps", "batch_size", "lr", "supervision")


def _json_safe(x):
    return json.loads(json.dumps(x, default=float))


class Objective:
    """Callable for ``study.optimize``: everything a worker needs, data loaded once."""

    def __init__(self, config: SearchConfig, study_path: Path | None,
                 data_progress: Callable[[int, int], None] | None = None) -> None:
        from explorer.data import open_dataset
        self.config = config
        self.space = SearchSpace.from_yaml(config.space)
        self.device_profile = get_device(config.device)
        self.budgets = [parse_budget(b) for b in config.budgets]
        self.train_cfg = config.train_config()
        self.torch_device = resolve_device(config.accelerator)
        self.train_set = open_dataset(config.data, "train", config.train_size, seed=config.seed,
                                      progress=data_progress)
        self.val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
        self.artifacts = None
        if config.keep_weights and study_path is not None:
            from optuna.artifacts import FileSystemArtifactStore
            (study_path / "artifacts").mkdir(parents=True, exist_ok=True)
            self.artifacts = FileSystemArtifactStore(str(study_path / "artifacts"))

    def candidate_for(self, trial: optuna.Trial) -> tuple[Candidate, str]:
        baseline = trial.user_attrs.get("baseline", "")
        if baseline:
            return BASELINES[baseline](), baseline
        return self.space.sample(trial), ""

    def losses_for(self, cost, path_losses: list[float]) -> dict[str, float]:
        out = {}
        for dist in self.budgets:
            out[dist.spec] = anytime_loss(cost.path_costs(self.device_profile, dist.kind), path_losses, dist)
        return out

    def __call__(self, trial: optuna.Trial):
        from explorer.model import build_network
        cfg = self.config
        candidate, baseline = self.candidate_for(trial)
        cost = candidate_cost(candidate, cfg.input_size)
        pm = cost.path_params_macs()
        latency = cost.path_latency_ms(self.device_profile)
        energy = cost.path_energy_j(self.device_profile)
        trial.set_user_attr("candidate", candidate.to_dict())
        trial.set_user_attr("candidate_key", candidate.key)
        trial.set_user_attr("params", [p for p, _ in pm])
        trial.set_user_attr("macs", [m for _, m in pm])
        trial.set_user_attr("latency_ms", latency)
        trial.set_user_attr("energy_j", energy)
        trial.set_user_attr("workloads", compact_workloads(cost))
        if not baseline:
            reason = self._rejection(pm, latency)
            if reason:
                trial.set_user_attr("rejected", reason)
                raise optuna.TrialPruned(reason)
            done = self._finished_twin(trial, candidate.key)
            if done is not None:
                # the sampler proposed a candidate already trained: reuse what was paid for
                for key in ("path_metrics", "train", "losses", "weights_artifact"):
                    if key in done.user_attrs:
                        trial.set_user_attr(key, done.user_attrs[key])
                trial.set_user_attr("duplicate_of", done.number)
                return done.values[0] if len(done.values) == 1 else tuple(done.values)
        primary = self.budgets[0]
        costs = cost.path_costs(self.device_profile, primary.kind)

        def report(step: int, metrics) -> None:
            if baseline or len(cfg.objectives) > 1:
                return
            value = anytime_loss(costs, list(metrics[cfg.metric]), primary)
            trial.report(value, step)
            if trial.should_prune():
                reason = f"pruned: anytime loss {value:.4f} at step {step} (worst quarter)"
                trial.set_user_attr("pruned", reason)
                raise Pruned(reason)

        import torch
        torch.manual_seed(cfg.seed)  # same candidate, same initial weights: results are repeatable
        net = build_network(candidate)
        with tempfile.TemporaryDirectory() as tmp:
            ckpt = Path(tmp) / f"{candidate.key}.pt"
            try:
                result = train(net, self.train_set, self.val_set, self.train_cfg, self.torch_device,
                               checkpoint=ckpt if self.artifacts else None, report=report,
                               val_limit=cfg.val_limit, checkpoint_every=10 ** 9)
            except Pruned as exc:
                raise optuna.TrialPruned(str(exc)) from None
            metrics = result.metrics
            path_metrics = _json_safe(metrics.drop(columns=["path"]).to_dict("records"))
            trial.set_user_attr("path_metrics", path_metrics)
            trial.set_user_attr("train", {"seconds": result.seconds, "steps": result.steps,
                                          "images_per_second": result.images_per_second})
            path_losses = [m[cfg.metric] for m in path_metrics]
            if any(not math.isfinite(v) for v in path_losses):
                raise FloatingPointError(f"non-finite validation {cfg.metric}: {path_losses}")
            losses = self.losses_for(cost, path_losses)
            trial.set_user_attr("losses", losses)
            if self.artifacts is not None:
                artifact = optuna.artifacts.upload_artifact(
                    artifact_store=self.artifacts, file_path=str(ckpt), study_or_trial=trial)
                trial.set_user_attr("weights_artifact", artifact)
        values = []
        for obj in cfg.objectives:
            if obj == "anytime_loss":
                values.append(losses[primary.spec])
            elif obj == "params":
                values.append(float(pm[-1][0]))
            elif obj == "macs":
                values.append(float(pm[-1][1]))
            else:
                values.append(latency[1] if len(latency) > 1 else 0.0)
        return values[0] if len(values) == 1 else tuple(values)

    @staticmethod
    def _finished_twin(trial: optuna.Trial, key: str) -> optuna.trial.FrozenTrial | None:
        for t in trial.study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
            if t.user_attrs.get("candidate_key") == key and not t.user_attrs.get("baseline") and \
                    "path_metrics" in t.user_attrs:
                return t
        return None

    def _rejection(self, pm, latency) -> str:
        cfg = self.config
        if cfg.max_params is not None and pm[-1][0] > cfg.max_params:
            return f"{pm[-1][0] / 1e6:.3f}M parameters > --max-params {cfg.max_params / 1e6:g}M"
        if cfg.max_first_exit_ms is not None and len(latency) > 1 and latency[1] > cfg.max_first_exit_ms:
            return f"first exit at {latency[1]:.2f} ms > --max-first-exit {cfg.max_first_exit_ms:g}ms"
        return ""


def make_sampler(config: SearchConfig, worker: int = 0) -> optuna.samplers.BaseSampler:
    seed = config.seed + 1000 * worker
    if len(config.objectives) > 1:
        return optuna.samplers.NSGAIISampler(seed=seed)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        # multivariate + group: the conditional LiDAR/ECU dimensions are modelled jointly
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=8, multivariate=True, group=True)


def make_pruner(config: SearchConfig) -> optuna.pruners.BasePruner:
    if not config.pruning or len(config.objectives) > 1:
        return optuna.pruners.NopPruner()
    # Early proxy losses rank candidates poorly: judge only in the second half of training, and
    # only prune the worst quarter (the baselines count towards the startup trials).
    return optuna.pruners.PercentilePruner(75.0, n_startup_trials=6,
                                           n_warmup_steps=max(config.train_steps // 2, 0))


def create_or_resume(config: SearchConfig, storage: optuna.storages.BaseStorage) -> optuna.Study:
    """Creates the study (and enqueues the baselines, once) or resumes it after checking that its
    settings match. Only the process that creates the study enqueues, so concurrent starts on one
    database never duplicate the baselines."""
    directions = ["minimize"] * len(config.objectives)
    try:
        study = optuna.create_study(study_name=config.study, storage=storage, directions=directions,
                                    sampler=make_sampler(config), pruner=make_pruner(config))
        created = True
    except optuna.exceptions.DuplicatedStudyError:
        study = optuna.load_study(study_name=config.study, storage=storage, sampler=make_sampler(config),
                                  pruner=make_pruner(config))
        created = False
    if created:
        space = SearchSpace.from_yaml(config.space)
        study.set_user_attr("config", config.to_dict())
        study.set_user_attr("explorer_version", __version__)
        study.set_user_attr("space_yaml", Path(space.source).read_text())
        study.set_user_attr("device_profile", get_device(config.device).to_dict())
        study.set_user_attr("created", time.strftime("%Y-%m-%d %H:%M:%S"))
        if config.baselines:
            for name in BASELINES:
                study.enqueue_trial({}, user_attrs={"baseline": name})
    else:
        old = study.user_attrs.get("config")
        if old:
            prev = SearchConfig.from_dict(old)
            diff = [k for k in SearchConfig.IDENTITY if getattr(prev, k) != getattr(config, k)]
            if diff:
                k = diff[0]
                raise UserError(
                    f"study '{config.study}' was created with {k}={getattr(prev, k)!r}, not "
                    f"{getattr(config, k)!r}: resume with the same settings, pick another --study, or "
                    "use `explorer rescore` for another device or budget")
    return study


@dataclass
class SearchOutcome:
    study: optuna.Study
    storage_url: str
    seconds: float
    interrupted_failed: int = 0


def run_worker(config_dict: dict, storage_url: str | None, n_trials: int | None, deadline: float | None,
               worker: int, reports: str, threads: int) -> None:
    """One worker process of a multi-process search (spawned)."""
    import torch
    torch.set_num_threads(max(threads, 1))
    config = SearchConfig.from_dict(config_dict)
    storage = open_storage(storage_url, config.study, workers=2, reports=Path(reports))
    study = optuna.load_study(study_name=config.study, storage=storage, sampler=make_sampler(config, worker),
                              pruner=make_pruner(config))
    objective = Objective(config, study_dir(config.study, Path(reports)))
    _optimize(study, objective, n_trials, deadline)


def _optimize(study: optuna.Study, objective: Objective, n_trials: int | None, deadline: float | None,
              callbacks: list | None = None) -> None:
    from optuna.study import MaxTrialsCallback
    from optuna.trial import TrialState
    cbs = list(callbacks or [])
    if n_trials is not None:
        cbs.append(MaxTrialsCallback(n_trials, states=(TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)))
        if len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL))) >= n_trials:
            return
    timeout = None if deadline is None else max(deadline - time.time(), 0.0)
    if timeout is not None and timeout <= 0:
        return
    study.optimize(objective, timeout=timeout, callbacks=cbs, catch=(Exception,), gc_after_trial=True)


def search(config: SearchConfig, storage_url: str | None = None, workers: int = 1,
           n_trials: int | None = None, timeout_s: float | None = 600.0, reports: Path = REPORTS_DIR,
           on_trial: Callable[[optuna.Study, optuna.trial.FrozenTrial], None] | None = None,
           on_poll: Callable[[optuna.Study], None] | None = None,
           on_data: Callable[[int, int], None] | None = None) -> SearchOutcome:
    """Runs (or resumes) the study until ``n_trials`` trials are done or ``timeout_s`` passes."""
    config.validate()
    if workers < 1:
        raise UserError("--workers must be at least 1")
    storage = open_storage(storage_url, config.study, workers, reports)
    study = create_or_resume(config, storage)
    # No worker of this run has started yet; on local storage nobody else can be running.
    failed = 0
    if storage_url is None or storage_url.startswith("sqlite"):
        failed = fail_interrupted_trials(study)
    if config.keep_weights:
        study.set_user_attr("artifacts_dir", str((study_dir(config.study, reports) / "artifacts").resolve()))
    url = storage_url or (f"journal:{reports / config.study / 'journal.log'}" if workers > 1
                          else f"sqlite:///{reports / config.study / 'study.db'}")
    t0 = time.time()
    deadline = None if timeout_s is None else t0 + timeout_s
    if workers == 1:
        objective = Objective(config, study_dir(config.study, reports), on_data)
        cb = [lambda s, t: on_trial(s, t)] if on_trial else []
        _optimize(study, objective, n_trials, deadline, cb)
    else:
        from explorer.data import open_dataset
        open_dataset(config.data, "val", config.train_size, progress=on_data)  # generate once, not per worker
        import multiprocessing as mp
        ctx = mp.get_context("spawn")
        threads = max(1, (os.cpu_count() or 1) // workers)
        procs = [ctx.Process(target=run_worker, args=(config.to_dict(), url, n_trials, deadline, i,
                                                      str(reports), threads))
                 for i in range(workers)]
        for p in procs:
            p.start()
        try:
            while any(p.is_alive() for p in procs):
                time.sleep(2.0)
                if on_poll:
                    on_poll(study)
        finally:
            for p in procs:
                p.join(timeout=5)
                if p.is_alive():
                    p.terminate()
    return SearchOutcome(study, url, time.time() - t0, failed)
