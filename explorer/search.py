"""The search: Optuna over a search space, minimising the anytime loss on a device.

Each trial samples a candidate, costs its paths on the device (no training), rejects it if a
constraint rules it out, estimates its per-path accuracy with an evaluator (a slice of the space's
trained supernet, about a second; or proxy training, reporting the anytime loss so hopeless ones are
pruned), and stores everything re-scoring needs. The paper's design, the same without early exits,
and a FastDepth-like network are the study's first trials (when the evaluator can estimate them),
tagged as baselines. A study ends by retraining its best candidates and the baselines stand-alone
with a longer recipe (the finalists): the winner a user reads about is always a retrained one.
"""

from __future__ import annotations

import dataclasses
import gc
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
from explorer.cost import candidate_cost, get_device, model_cost
from explorer.errors import UserError
from explorer.results import compact_workloads
from explorer.space import (Candidate, SearchSpace, fastdepth_candidate, paper_candidate,
                            paper_nee_candidate)
from explorer.evaluators import EVALUATORS, ProxyEvaluator, SupernetEvaluator
from explorer.planning import Plan, TimeLimit
from explorer.retry import StopAfterTrials, counted_trials, guarded, resume_interrupted, set_objective_names
from explorer.storage import REPORTS_DIR, open_storage, study_dir
from explorer.train import PROXY, Pruned, TrainConfig, resolve_device

BASELINES: dict[str, Callable[[], Candidate]] = {
    "paper": paper_candidate, "paper-nee": paper_nee_candidate, "fastdepth": fastdepth_candidate}
#: what a study compares against unless told otherwise (--baselines)
DEFAULT_BASELINES = tuple(BASELINES)


def baseline_model(name: str):
    """The candidate, or the reference network (:class:`~explorer.model.reference.ReferenceModel`),
    that the baseline ``name`` stands for."""
    from explorer.model.reference import REFERENCES, ReferenceModel
    if name in BASELINES:
        return BASELINES[name]()
    if name in REFERENCES:
        return ReferenceModel(name)
    raise UserError(f"unknown baseline '{name}': use {', '.join(BASELINES)} or a reference network "
                    f"({', '.join(REFERENCES)})")
OBJECTIVES = ("anytime_loss", "params", "macs", "first_exit_ms")


def objective_names(config: "SearchConfig") -> list[str]:
    """What each objective is, for optuna-dashboard and Optuna's plots: anytime_loss[time:uniform:33ms]."""
    return [f"anytime_loss[{config.budgets[0]}]" if o == "anytime_loss" else o for o in config.objectives]


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
    baselines: tuple[str, ...] = DEFAULT_BASELINES   # () = none (--no-baselines)
    pruning: bool = True
    keep_weights: bool = True
    accelerator: str = "auto"
    evaluator: str = "auto"                      # supernet for dense labels, proxy for self-supervision
    supernet: str | None = None                  # a supernet file (default: the cached one)
    supernet_steps: int = 600
    finalists: int = 3                           # retrained stand-alone at the end (0 = none)
    finalist_steps: int = 300
    max_retries: int = 2          # an interrupted trial (killed, Ctrl-C, lost worker) is tried again
    supervision: str = "supervised"              # supervised | self | mixed (see explorer.selfsup)
    poses: str = "net"                           # self-supervision's camera motion: net | given
    hints: bool = False                          # depth hints (explorer.depth_hints; poses given)

    def __post_init__(self) -> None:
        if self.evaluator == "auto":  # the supernet is trained with dense labels; self-supervision trains alone
            object.__setattr__(self, "evaluator", "supernet" if self.supervision == "supervised" else "proxy")
        # studies made before --baselines stored on (True) or off (False)
        baselines = self.baselines
        if isinstance(baselines, bool):
            baselines = DEFAULT_BASELINES if baselines else ()
        object.__setattr__(self, "baselines", tuple(baselines))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("budgets", "objectives", "input_size", "train_size", "baselines"):
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
                                   seed=self.seed, supervision=self.supervision, poses=self.poses,
                                   hints=self.hints,
                                   eval_every=max(2 * self.train_steps // 3, 1) if self.pruning else 0)

    def finalist_config(self, seed: int | None = None) -> TrainConfig:
        """The longer stand-alone recipe of the finalists (and of the baselines beside them)."""
        return dataclasses.replace(self.train_config(), steps=self.finalist_steps, eval_every=0,
                                   seed=self.seed if seed is None else seed)

    def supernet_recipe(self):
        from explorer.supernet import SupernetRecipe
        return SupernetRecipe(steps=self.supernet_steps, batch_size=self.batch_size, input_size=self.train_size,
                              lr=self.lr, lr_end=self.lr / 10, seed=self.seed)

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
        if self.evaluator not in EVALUATORS:
            raise UserError(f"--evaluator {self.evaluator}: use one of {list(EVALUATORS)}")
        if self.supernet and self.evaluator != "supernet":
            raise UserError("--supernet FILE is read by the supernet evaluator only: drop --evaluator proxy "
                            "(or give --evaluator supernet)")
        if self.supernet_steps < 1 or self.finalist_steps < 1:
            raise UserError("--supernet-steps and --finalist-steps must be at least 1")
        if self.finalists < 0:
            raise UserError("--finalists must be 0 (none) or more")
        if self.max_retries < 0:
            raise UserError("--max-retries must be 0 or more")
        if len(set(self.baselines)) != len(self.baselines):
            raise UserError(f"--baselines {','.join(self.baselines)}: a baseline is named twice")
        for name in self.baselines:
            model = baseline_model(name)
            if not isinstance(model, Candidate):
                h, w = self.train_size
                if h % model.stride or w % model.stride or min(h, w) < model.min_side:
                    raise UserError(f"--baselines {name} needs --train-size sides divisible by {model.stride} and "
                                    f"at least {model.min_side}, got {h}x{w} (e.g. 64x64)")
        self.train_config().validate()
        space = SearchSpace.from_yaml(self.space)
        if "int8" in space.precision and "int8" not in get_device(self.device).precisions:
            raise UserError(f"the space {space.name} lists precision int8, but the {self.device} profile prices no "
                            "int8 graphs: give --device a profile that does (`explorer calibrate --out mybox.yaml` "
                            "times int8 layers) or keep the space's precision at fp32")
        from explorer.data import parse_data_spec
        if self.supervision != "supervised" and not parse_data_spec(self.data).is_sequence:
            raise UserError(f"--supervision {self.supervision} needs sequence data (--data synthetic-seq, "
                            "kitti-seq:DRIVE or frames:FOLDER)")
        if self.supervision != "supervised" and self.evaluator == "supernet":
            raise UserError(f"--supervision {self.supervision}: the supernet is trained with dense labels; "
                            "add --evaluator proxy to search with self-supervised training")

    # settings that change what a trial's value means: a resumed study must keep them
    IDENTITY = ("space", "device", "budgets", "data", "objectives", "metric", "input_size", "train_size",
                "train_steps", "batch_size", "lr", "evaluator", "supernet_steps", "supervision", "poses", "hints")

    @classmethod
    def defaults_of_older_studies(cls) -> dict:
        """Settings a study made before they existed was run with."""
        return {"evaluator": "proxy", "finalists": 0, "supervision": "supervised", "poses": "net", "hints": False}


def _with_hints(config: SearchConfig, train_set, progress: Callable[[int, int], None] | None):
    """The training frames with their depth hints when the study uses them: computed once, before the
    first trial (with progress), then read from the cache by every trial and worker."""
    if not config.hints:
        return train_set
    from explorer.depth_hints import with_hints
    return with_hints(train_set, progress=progress)


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
        self.train_set = _with_hints(config, open_dataset(config.data, "train", config.train_size, seed=config.seed,
                                                          progress=data_progress), data_progress)
        self.val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
        if config.evaluator == "supernet":
            from explorer.supernet import default_path
            file = config.supernet or default_path(self.space, config.data, config.supernet_recipe())
            calibration = open_dataset(config.data, "train", config.train_size, train_augment=False)
            self.evaluator = SupernetEvaluator(file, self.space, calibration, self.val_set, self.torch_device,
                                               val_limit=config.val_limit)
        else:
            self.evaluator = ProxyEvaluator(self.train_set, self.val_set, self.train_cfg, self.torch_device,
                                            val_limit=config.val_limit, seed=config.seed)
        self.artifacts = None
        if config.keep_weights and study_path is not None:
            from optuna.artifacts import FileSystemArtifactStore
            (study_path / "artifacts").mkdir(parents=True, exist_ok=True)
            self.artifacts = FileSystemArtifactStore(str(study_path / "artifacts"))

    def candidate_for(self, trial: optuna.Trial) -> tuple[Candidate, str]:
        baseline = trial.user_attrs.get("baseline", "")
        if baseline:
            return baseline_model(baseline), baseline
        return self.space.sample(trial), ""

    def losses_for(self, cost, path_losses: list[float]) -> dict[str, float]:
        out = {}
        for dist in self.budgets:
            out[dist.spec] = anytime_loss(cost.path_costs(self.device_profile, dist.kind), path_losses, dist)
        return out

    def describe(self, trial, candidate):
        """Costs every path of ``candidate`` (or of a reference network) and stores what re-scoring
        needs on ``trial``."""
        cost = model_cost(candidate, self.config.input_size)
        pm = cost.path_params_macs()
        latency = cost.path_latency_ms(self.device_profile)
        what = {"candidate": candidate.to_dict()} if isinstance(candidate, Candidate) else {"reference": candidate.name}
        attrs = {**what, "candidate_key": candidate.key, "params": [p for p, _ in pm],
                 "macs": [m for _, m in pm], "latency_ms": latency,
                 "energy_j": cost.path_energy_j(self.device_profile), "workloads": compact_workloads(cost)}
        for k, v in attrs.items():
            trial.set_user_attr(k, v)
        return cost, pm, latency

    def values(self, losses: dict[str, float], pm, latency):
        values = []
        for obj in self.config.objectives:
            if obj == "anytime_loss":
                values.append(losses[self.budgets[0].spec])
            elif obj == "params":
                values.append(float(pm[-1][0]))
            elif obj == "macs":
                values.append(float(pm[-1][1]))
            else:
                values.append(latency[1] if len(latency) > 1 else 0.0)
        return values[0] if len(values) == 1 else tuple(values)

    def __call__(self, trial: optuna.Trial):
        cfg = self.config
        candidate, baseline = self.candidate_for(trial)
        cost, pm, latency = self.describe(trial, candidate)
        if not baseline:
            reason = self._rejection(pm, latency)
            if reason:
                trial.set_user_attr("rejected", reason)
                raise optuna.TrialPruned(reason)
            done = self._finished_twin(trial, candidate.key)
            if done is not None:
                # the sampler proposed a candidate already evaluated: reuse what was paid for
                for key in ("path_metrics", "train", "losses", "weights_artifact", "evaluator", "path_metrics_fp32",
                            "quantization", "int8_graphs"):
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

        keep = self.artifacts is not None and self.evaluator.name == "proxy"
        with tempfile.TemporaryDirectory() as tmp:
            ckpt = Path(tmp) / f"{candidate.key}.pt"
            try:
                result = self.evaluator(candidate, checkpoint=ckpt if keep else None, report=report)
            except Pruned as exc:
                raise optuna.TrialPruned(str(exc)) from None
            path_metrics = _json_safe(result.metrics.drop(columns=["path"]).to_dict("records"))
            if candidate.precision == "int8":
                if result.info["evaluator"] == "supernet":   # stage-by-stage evaluation left the slice's BN as it was
                    from explorer.evaluators import recalibrate_batchnorm
                    recalibrate_batchnorm(result.network, self.evaluator.calibration)
                path_metrics = self.quantized(trial, result.network, path_metrics, cost)
            trial.set_user_attr("path_metrics", path_metrics)
            trial.set_user_attr("evaluator", _json_safe(result.info))
            if result.info["evaluator"] == "proxy":
                trial.set_user_attr("train", {k: result.info[k] for k in ("seconds", "steps", "images_per_second")})
            path_losses = [m[cfg.metric] for m in path_metrics]
            if any(not math.isfinite(v) for v in path_losses):
                raise FloatingPointError(f"non-finite validation {cfg.metric}: {path_losses}")
            losses = self.losses_for(cost, path_losses)
            trial.set_user_attr("losses", losses)
            if keep:
                artifact = optuna.artifacts.upload_artifact(
                    artifact_store=self.artifacts, file_path=str(ckpt), study_or_trial=trial)
                trial.set_user_attr("weights_artifact", artifact)
        return self.values(losses, pm, latency)

    def quantized(self, trial, net, path_metrics: list[dict], cost) -> list[dict]:
        """An int8 candidate's metrics: those of its fp32 weights ``net`` (on the frames every trial
        uses) times what quantizing its graphs does to each path, measured with onnxruntime
        (explorer.quantize); both, and the change, are kept on ``trial``. The graphs quantized are those
        the device profile prices int8 (``CandidateCost.int8_graphs``), as its latency assumes."""
        from explorer.quantize import quantization_effect
        net.eval()
        graphs = cost.int8_graphs(self.device_profile)
        effect = quantization_effect(net, self.config.train_size, self.config.data,
                                     eval_frames=self.config.val_limit or 32, stages=graphs)
        trial.set_user_attr("int8_graphs", list(graphs))
        trial.set_user_attr("path_metrics_fp32", path_metrics)
        trial.set_user_attr("quantization", _json_safe({k: effect[k] for k in ("rmse_degradation", "frames")}))
        return [{k: v * r.get(k, 1.0) if isinstance(v, (int, float)) else v for k, v in m.items()}
                for m, r in zip(path_metrics, effect["ratios"])]

    @staticmethod
    def _finished_twin(trial: optuna.Trial, key: str) -> optuna.trial.FrozenTrial | None:
        for t in trial.study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
            if t.user_attrs.get("candidate_key") == key and not t.user_attrs.get("baseline") and \
                    "path_metrics" in t.user_attrs and "finalist" not in t.user_attrs:
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
            skipped = {}
            for name in config.baselines:
                model = baseline_model(name)
                if not isinstance(model, Candidate):
                    skipped[name] = ("a reference network, outside every space: it is compared after retraining "
                                     "(finalists) only")
                    continue
                if config.evaluator == "supernet" and not space.contains(model):
                    skipped[name] = (f"outside the space '{space.name}': the supernet cannot estimate it, so it "
                                     "is compared after retraining (finalists) only")
                    continue
                study.enqueue_trial({}, user_attrs={"baseline": name})
            study.set_user_attr("baselines_not_estimated", skipped)
        set_objective_names(study, objective_names(config))
    else:
        old = study.user_attrs.get("config")
        if old:
            prev = SearchConfig.from_dict({**SearchConfig.defaults_of_older_studies(), **old})
            diff = [k for k in SearchConfig.IDENTITY if getattr(prev, k) != getattr(config, k)]
            if diff:
                k = diff[0]
                raise UserError(
                    f"study '{config.study}' was created with {k}={getattr(prev, k)!r}, not "
                    f"{getattr(config, k)!r}: resume with the same settings, pick another --study, or "
                    "use `explorer rescore` for another device or budget")
        set_objective_names(study, objective_names(config))  # studies made before objectives had names
    return study


@dataclass
class SearchOutcome:
    study: optuna.Study
    storage_url: str
    seconds: float
    interrupted_failed: int = 0
    retried: dict[int, int] = dataclasses.field(default_factory=dict)   # interrupted trial -> its retry
    not_retried: list[int] = dataclasses.field(default_factory=list)    # interrupted past --max-retries
    config: SearchConfig | None = None     # as run: a --time-limit plan may have sized its steps
    plan: "Plan | None" = None


def run_worker(config_dict: dict, storage_url: str | None, n_trials: int | None, deadline: float | None,
               worker: int, reports: str, threads: int) -> None:
    """One worker process of a multi-process search (spawned)."""
    import torch
    torch.set_num_threads(max(threads, 1))
    config = SearchConfig.from_dict(config_dict)
    storage = open_storage(storage_url, config.study, workers=2, reports=Path(reports), max_retries=config.max_retries)
    study = optuna.load_study(study_name=config.study, storage=storage, sampler=make_sampler(config, worker),
                              pruner=make_pruner(config))
    objective = Objective(config, study_dir(config.study, Path(reports)))
    _optimize(study, objective, n_trials, deadline)


def _optimize(study: optuna.Study, objective: Objective, n_trials: int | None, deadline: float | None,
              callbacks: list | None = None) -> None:
    cbs = list(callbacks or [])
    if n_trials is not None:
        # interrupted trials do not count (their retries do): see explorer.retry
        cbs.append(StopAfterTrials(n_trials))
        if counted_trials(study) >= n_trials:
            return
    timeout = None if deadline is None else max(deadline - time.time(), 0.0)
    if timeout is not None and timeout <= 0:
        return
    # everything loaded so far (torch, data, the evaluator's batches) lives as long as the worker:
    # frozen, the collection after each trial skips it (0.1-0.25 s a trial otherwise)
    gc.freeze()
    study.optimize(guarded(objective, objective.config.max_retries), timeout=timeout, callbacks=cbs,
                   catch=(Exception,), gc_after_trial=True)


def ensure_supernet(config: SearchConfig, progress: Callable[[int, int, dict], None] | None = None,
                    data_progress: Callable[[int, int], None] | None = None) -> Path | None:
    """The supernet file the study's evaluator reads: the given one (checked), or the cached one for
    (space, data, recipe), trained here first if it is missing or unfinished."""
    if config.evaluator != "supernet":
        return None
    from explorer.supernet import default_path, load_supernet, train_supernet
    space = SearchSpace.from_yaml(config.space)
    if config.supernet:
        load_supernet(config.supernet, space)  # one clear line if it is foreign, corrupt or unfinished
        return Path(config.supernet)
    return train_supernet(space, config.data, config.supernet_recipe(), default_path(
        space, config.data, config.supernet_recipe()), resolve_device(config.accelerator),
        progress=progress, data_progress=data_progress)


def _existing_config(storage: optuna.storages.BaseStorage, name: str) -> dict | None:
    try:
        return optuna.load_study(study_name=name, storage=storage).user_attrs.get("config")
    except KeyError:
        return None


def _cached_supernet_steps(config: SearchConfig) -> list[int]:
    """Step counts of the finished supernets cached for this space, data and recipe (steps aside)."""
    from explorer.planning import MAX_SUPERNET_STEPS, STEP_GRID
    from explorer.supernet import default_path, read_supernet
    space = SearchSpace.from_yaml(config.space)
    found = []
    for steps in sorted({*range(STEP_GRID, MAX_SUPERNET_STEPS + 1, STEP_GRID), config.supernet_steps}):
        path = default_path(space, config.data, dataclasses.replace(config.supernet_recipe(), steps=steps))
        try:
            if path.is_file() and read_supernet(path).get("complete"):
                found.append(steps)
        except UserError:
            continue  # a broken file is trained again in its place
    return found


def baseline_load(config: SearchConfig, speeds=None) -> float:
    """The baselines' retraining in paper designs' worth, for the time plan: each its measured training
    step over the paper design's (``speeds``), or without a measurement one for a candidate and for a
    reference network its MACs at the training size over the paper design's (which over-counts the
    ResNets: about 1.5x measured against 3.34x by MACs for S2D-ResNet-18,
    benchmarks/bench_baseline_training.py)."""
    paper = candidate_cost(paper_candidate(), config.train_size).path_params_macs()[-1][1]
    load = 0.0
    for name in config.baselines:
        measured = speeds.relative_training(name) if speeds is not None else None
        model = baseline_model(name)
        if measured is not None:
            load += measured
        elif isinstance(model, Candidate):
            load += 1.0
        else:
            load += max(1.0, model_cost(model, config.train_size).path_params_macs()[-1][1] / paper)
    return load


def plan_search(config: SearchConfig, storage: optuna.storages.BaseStorage, limit: "TimeLimit",
                sampling_s: float | None, on_data: Callable[[int, int], None] | None = None):
    """(config as it will run, plan, speeds): the data generated, the machine measured, the run sized
    to what is left of ``limit`` (see explorer.planning)."""
    from explorer import planning
    from explorer.data import open_dataset
    free = set(limit.free)
    old = _existing_config(storage, config.study)
    if old and "supernet_steps" in free and "supernet_steps" in old:
        config = dataclasses.replace(config, supernet_steps=int(old["supernet_steps"]))  # the study's supernet
        free.discard("supernet_steps")
    train_set = _with_hints(config, open_dataset(config.data, "train", config.train_size, seed=config.seed,
                                                 progress=on_data), on_data)
    val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
    os.sync()  # data just generated is still being written back: measured then, steps read 1.6-2x slow
    trains_supernet = config.evaluator == "supernet" and not config.supernet
    cached = _cached_supernet_steps(config) if trains_supernet else []
    must_measure_supernet = trains_supernet and ("supernet_steps" in free or config.supernet_steps not in cached)
    speeds = planning.measure_speeds(config, train_set, val_set, resolve_device(config.accelerator),
                                     supernet=must_measure_supernet,
                                     baselines=_measured_baselines(config) if config.finalists else ())
    trial_s = 0.0 if config.evaluator == "supernet" else planning.SAFETY * (
        config.train_steps * speeds.retrain_step_s + speeds.retrain_eval_s)

    def plan(steps: int, steps_free: bool, is_cached: bool):
        return planning.plan_run(
            limit.remaining(), limit.seconds, speeds, sampling_s=sampling_s, supernet_steps=steps,
            supernet_free=steps_free, supernet_cached=is_cached or not trains_supernet,
            finalists=config.finalists, finalists_free="finalists" in free, finalist_steps=config.finalist_steps,
            finalist_steps_free="finalist_steps" in free,
            baselines=baseline_load(config, speeds), baseline_count=len(config.baselines), trial_s=trial_s)

    chosen = plan(config.supernet_steps, "supernet_steps" in free, config.supernet_steps in cached)
    larger = [s for s in cached if s >= chosen.supernet_steps]
    if "supernet_steps" in free and larger:  # a cached supernet at least as trained costs nothing
        chosen = plan(max(larger), False, True)
    config = dataclasses.replace(config, supernet_steps=chosen.supernet_steps, finalists=chosen.finalists,
                                 finalist_steps=chosen.finalist_steps)
    return config, chosen, speeds


def _measured_baselines(config: SearchConfig) -> tuple[str, ...]:
    """The baselines whose training is measured for the plan (the paper design's is the step itself)."""
    return tuple(n for n in config.baselines if baseline_model(n) != paper_candidate())


def _measure_again(config: SearchConfig, speeds, finalists: tuple[Candidate, ...] = ()):
    """The retraining speeds measured again, the ``finalists`` chosen by now with them (the supernet's
    is kept: it is trained by now)."""
    from explorer import planning
    from explorer.data import open_dataset
    train_set = open_dataset(config.data, "train", config.train_size, seed=config.seed)
    val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
    fresh = planning.measure_speeds(config, train_set, val_set, resolve_device(config.accelerator), supernet=False,
                                    baselines=_measured_baselines(config), finalists=finalists)
    return dataclasses.replace(fresh, supernet_step_s=speeds.supernet_step_s)


def search(config: SearchConfig, storage_url: str | None = None, workers: int = 1,
           n_trials: int | None = None, timeout_s: float | None = 600.0, reports: Path = REPORTS_DIR,
           on_trial: Callable[[optuna.Study, optuna.trial.FrozenTrial], None] | None = None,
           on_poll: Callable[[optuna.Study], None] | None = None,
           on_data: Callable[[int, int], None] | None = None,
           on_supernet: Callable[[int, int, dict], None] | None = None,
           on_finalist: Callable[[int, int, str], None] | None = None,
           time_limit: "TimeLimit | None" = None,
           on_plan: Callable[["Plan"], None] | None = None) -> SearchOutcome:
    """Runs (or resumes) the study until ``n_trials`` trials are done or ``timeout_s`` passes (the
    supernet's training and the finalists' retraining are not counted), then retrains the finalists.
    With ``time_limit`` the whole run is sized to it first (explorer.planning): ``timeout_s`` is then
    the most sampling may take."""
    config.validate()
    if workers < 1:
        raise UserError("--workers must be at least 1")
    storage = open_storage(storage_url, config.study, workers, reports, max_retries=config.max_retries)
    plan = speeds = None
    sampling_cap = timeout_s
    if config.supernet:
        ensure_supernet(config)  # a foreign or corrupt file is one line before anything is measured
    wanted = (config.finalists, config.finalist_steps)   # before a plan shrinks them
    if time_limit is not None:
        config, plan, speeds = plan_search(config, storage, time_limit, timeout_s, on_data)
        timeout_s = plan.sampling_s
        if on_plan:
            on_plan(plan)
    study = create_or_resume(config, storage)
    if plan is not None:
        study.set_user_attr("plan", plan.to_dict())
    # No worker of this run has started yet; on local storage nobody else can be running: its RUNNING
    # trials were interrupted (kill -9), and are tried again. RDB storage does this by heartbeat.
    failed, retried, not_retried = 0, {}, []
    if storage_url is None or storage_url.startswith("sqlite"):
        failed, retried, not_retried = resume_interrupted(study, config.max_retries)
    if config.keep_weights:
        study.set_user_attr("artifacts_dir", str((study_dir(config.study, reports) / "artifacts").resolve()))
    url = storage_url or (f"journal:{reports / config.study / 'journal.log'}" if workers > 1
                          else f"sqlite:///{reports / config.study / 'study.db'}")
    supernet = ensure_supernet(config, on_supernet, on_data)
    if supernet is not None:
        study.set_user_attr("supernet", str(supernet.resolve()))
    if plan is not None:
        from explorer.planning import replan_sampling
        plan = replan_sampling(plan, time_limit.remaining(), sampling_cap)
        timeout_s = plan.sampling_s
        study.set_user_attr("plan", plan.to_dict())
        if on_plan:
            on_plan(plan)
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
    if plan is not None and (config.finalists or config.baselines):
        from explorer.finalists import choose_finalists, finalist_trials
        from explorer.planning import replan_finalists
        done = [t.user_attrs["finalist"]["recipe"]["steps"] for t in finalist_trials(study)]
        steps_free = "finalist_steps" in time_limit.free and not done   # a resumed study keeps its recipe
        # the machine may be busier or freer than when it was first measured, and the finalists are known
        # now: measure it again, on them (seconds)
        count = max(config.finalists, wanted[0]) if "finalists" in time_limit.free else config.finalists
        chosen = tuple(Candidate.from_dict(t.user_attrs["candidate"]) for t in choose_finalists(study, count))
        speeds = _measure_again(config, speeds, chosen)
        plan = replan_finalists(plan, time_limit.remaining(), speeds, baseline_load(config, speeds),
                                steps_free=steps_free, finalists_free="finalists" in time_limit.free,
                                baseline_count=len(config.baselines), wanted=wanted)
        config = dataclasses.replace(config, finalists=plan.finalists,
                                     finalist_steps=plan.finalist_steps if steps_free or not done else max(done))
        study.set_user_attr("plan", plan.to_dict())
        if on_plan:
            on_plan(plan)
    if config.finalists:
        from explorer.finalists import finalist_trials, retrain_finalists
        # the re-plan stood on a few steps' measurement: finalists it dropped are retrained after the
        # others when the time those took says they still fit
        extra, deadline = 0, None
        if plan is not None and "finalists" in time_limit.free:
            from explorer.planning import RESERVE_S
            extra = max(wanted[0] - config.finalists, 0)
            deadline = time_limit.started + time_limit.seconds - RESERVE_S
        retrain_finalists(study, config, reports, progress=on_finalist, extra=extra, deadline=deadline)
        retrained = sum(1 for t in finalist_trials(study) if not t.user_attrs.get("baseline")
                        and t.user_attrs["finalist"].get("recipe") == config.finalist_config().to_dict())
        if plan is not None and retrained > plan.finalists:
            plan = dataclasses.replace(plan, finalists=retrained, changes=plan.changes + (
                f"{retrained - plan.finalists} more finalist(s) retrained: the others took less than planned",))
            config = dataclasses.replace(config, finalists=retrained)
            study.set_user_attr("plan", plan.to_dict())
            if on_plan:
                on_plan(plan)
    return SearchOutcome(study, url, time.time() - t0, failed, retried, not_retried, config, plan)
