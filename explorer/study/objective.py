"""One trial of a search: sample a candidate, cost its paths on the device, check the constraints,
estimate its accuracy with the evaluator, and store everything re-scoring needs."""


import math
from pathlib import Path
from typing import Callable

import optuna
# imported with this module, not in Objective.__init__: optuna.artifacts keeps the ImportErrors of its
# optional back-ends (boto3, google-cloud) with their tracebacks, whose frames would keep the first
# Objective that imported it, with its evaluator's caches (a gigabyte), alive as long as the process
from optuna.artifacts import FileSystemArtifactStore

from explorer.anytime import anytime_loss
from explorer.cost import model_cost
from explorer.data import open_dataset
from explorer.deploy.export import quantization_effect
from explorer.files import scratch_dir
from explorer.model.shipped import ship
from explorer.space import Candidate
from explorer.study.config import SearchConfig, StudyContext, baseline_model, json_safe
from explorer.study.records import record, trial_record
from explorer.study.results import compact_workloads
from explorer.study.sampling import unseen
from explorer.supernet import default_path
from explorer.supernet.evaluators import ProxyEvaluator, SupernetEvaluator
from explorer.training.depth_hints import with_hints
from explorer.training.deployment import DeploymentData
from explorer.training.train import Pruned, resolve_accelerator


def hinted_if_asked(config: SearchConfig, train_set, progress: Callable[[int, int], None] | None):
    """The training frames with their depth hints when the study uses them: computed once, before the
    first trial (with progress), then read from the cache by every trial and worker."""
    if not config.hints:
        return train_set
    return with_hints(train_set, progress=progress)


class FinishedTwins:
    """The first complete trial that evaluated each candidate (not a baseline or a finalist's
    retraining): what a trial reuses when the sampler proposes a candidate again. The index is kept up
    to date with the new complete trials only (a finished trial no longer changes), so a look-up costs
    the same at trial 100 and at trial 10,000 (bench_long_study)."""

    def __init__(self) -> None:
        self._first: dict[str, optuna.trial.FrozenTrial] = {}
        self._indexed: set[int] = set()

    def find(self, study: optuna.Study, key: str) -> optuna.trial.FrozenTrial | None:
        complete = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
        for t in unseen(complete, self._indexed):
            self._indexed.add(t.number)
            rec = trial_record(t)
            if not rec.baseline and rec.path_metrics is not None and rec.retraining is None:
                first = self._first.setdefault(rec.candidate_key, t)
                if t.number < first.number:   # an earlier trial that finished later
                    self._first[rec.candidate_key] = t
        return self._first.get(key)


class Objective:
    """Callable for ``study.optimize``: everything a worker needs, data loaded once."""

    def __init__(self, context: StudyContext, study_path: Path | None,
                 data_progress: Callable[[int, int], None] | None = None) -> None:
        config = self.config = context.config
        self.space, self.device_profile, self.budgets = context.space, context.device, list(context.budgets)
        self.train_cfg = config.train_config()
        self.torch_device = resolve_accelerator(config.accelerator)
        self.train_set = hinted_if_asked(config, open_dataset(config.data, "train", config.train_size, seed=config.seed,
                                                          progress=data_progress), data_progress)
        self.val_set = open_dataset(config.data, "val", config.train_size, train_augment=False)
        if config.evaluator == "supernet":
            file = config.supernet or default_path(self.space, config.data, config.supernet_recipe())
            calibration = open_dataset(config.data, "train", config.train_size, train_augment=False)
            # the study's own supernet may be short of its steps (its time limit stopped it); a given one was checked
            self.evaluator = SupernetEvaluator(file, self.space, calibration, self.val_set, self.torch_device,
                                               val_limit=config.val_limit, require_complete=bool(config.supernet))
            # the evaluator keeps batches of the first frames: the training set (0.5 GB of frames for the
            # default data) is not held while sampling (deployment_data opens it again if asked)
            self.train_set = None
        else:
            self.evaluator = ProxyEvaluator(self.train_set, self.val_set, self.train_cfg, self.torch_device,
                                            val_limit=config.val_limit, seed=config.seed)
        self._deployment: DeploymentData | None = None
        self.twins = FinishedTwins()
        self.artifacts = None
        if config.keep_weights and study_path is not None:
            (study_path / "artifacts").mkdir(parents=True, exist_ok=True)
            self.artifacts = FileSystemArtifactStore(str(study_path / "artifacts"))

    def deployment_data(self) -> DeploymentData:
        """The frames a finalist trains and is measured on: the study's training set, and the training and
        validation sets at the deployment size (--input-size; opened once, when first asked for)."""
        if self._deployment is None:
            cfg = self.config
            train_set = self.train_set if self.train_set is not None else hinted_if_asked(
                cfg, open_dataset(cfg.data, "train", cfg.train_size, seed=cfg.seed), None)
            if tuple(cfg.input_size) == tuple(cfg.train_size):
                self._deployment = DeploymentData(train_set, train_set, self.val_set)
            else:
                deploy_train = hinted_if_asked(cfg, open_dataset(cfg.data, "train", cfg.input_size, seed=cfg.seed), None)
                self._deployment = DeploymentData(train_set, deploy_train, open_dataset(
                    cfg.data, "val", cfg.input_size, train_augment=False))
        return self._deployment

    def candidate_for(self, trial: optuna.Trial) -> tuple[Candidate, str]:
        baseline = trial_record(trial).baseline or ""
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
        what = {"candidate": candidate.to_dict()} if isinstance(candidate, Candidate) else {"reference": candidate.name}
        record(trial, **what, candidate_key=candidate.key)
        return self._record_costs(trial, model_cost(candidate, self.config.input_size))

    def _record_costs(self, trial, cost):
        pm = cost.path_params_macs()
        latency = cost.path_latency_ms(self.device_profile)
        record(trial, params=[p for p, _ in pm], macs=[m for _, m in pm], latency_ms=latency,
               energy_j=cost.path_energy_j(self.device_profile), workloads=compact_workloads(cost))
        return cost, pm, latency

    def shipped(self, trial, candidate, costs: tuple, path_metrics: list[dict]) -> tuple[tuple, list[dict]]:
        """The network that ships from the trained ``candidate`` (explorer.model.shipped): its exits that
        do not improve on an earlier path by the study's metric are dropped unless --keep-every-exit, and
        the trial's costs and per-path figures become the shipped network's. ``costs``: (cost, params and
        MACs, latency) of the trained network; returns them and the figures, those of what ships."""
        if not isinstance(candidate, Candidate):
            return costs, path_metrics
        shipped = ship(candidate, [m[self.config.metric] for m in path_metrics], self.config.keep_every_exit)
        if not shipped.dropped:
            return costs, path_metrics
        kept = self._record_costs(trial, model_cost(shipped.candidate, self.config.input_size))
        record(trial, shipped={"candidate": shipped.candidate.to_dict(), "trained_paths": list(shipped.paths),
                               "dropped": [d.to_dict() for d in shipped.dropped]})
        if candidate.precision == "int8":   # what quantizing did, for the paths that ship
            fp32, effect = trial.user_attrs.get("path_metrics_fp32"), trial.user_attrs.get("quantization")
            record(trial, int8_graphs=list(kept[0].int8_graphs(self.device_profile)),
                   **({"path_metrics_fp32": [fp32[p] for p in shipped.paths]} if fp32 else {}),
                   **({"quantization": {**effect, "rmse_degradation": [
                       effect["rmse_degradation"][p] for p in shipped.paths]}} if effect else {}))
        return kept, [path_metrics[p] for p in shipped.paths]

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
                record(trial, rejected=reason)
                raise optuna.TrialPruned(reason)
            done = self.twins.find(trial.study, candidate.key)
            if done is not None:
                # the sampler proposed a candidate already evaluated: reuse what was paid for
                paid = trial_record(done)
                record(trial, **{key: getattr(paid, key) for key in (
                    "path_metrics", "train", "losses", "weights_artifact", "evaluator", "path_metrics_fp32",
                    "quantization", "int8_graphs", "shipped", "params", "macs", "latency_ms", "energy_j",
                    "workloads")}, duplicate_of=done.number)
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
                record(trial, pruned=reason)
                raise Pruned(reason)

        keep = self.artifacts is not None and self.evaluator.name == "proxy"
        with scratch_dir("trial") as tmp:
            ckpt = Path(tmp) / f"{candidate.key}.pt"
            try:
                result = self.evaluator(candidate, checkpoint=ckpt if keep else None, report=report)
            except Pruned as exc:
                raise optuna.TrialPruned(str(exc)) from None
            path_metrics = json_safe(result.metrics.drop(columns=["path"]).to_dict("records"))
            if candidate.precision == "int8":   # a stage-by-stage evaluation made no network
                net = result.network if result.network is not None else self.evaluator.network_of(candidate)
                path_metrics = self.quantized(trial, net, path_metrics, cost)
            (cost, pm, latency), path_metrics = self.shipped(trial, candidate, (cost, pm, latency), path_metrics)
            record(trial, path_metrics=path_metrics, evaluator=json_safe(result.info))
            if result.info["evaluator"] == "proxy":
                record(trial, train={k: result.info[k] for k in ("seconds", "steps", "images_per_second")})
            path_losses = [m[cfg.metric] for m in path_metrics]
            if any(not math.isfinite(v) for v in path_losses):
                raise FloatingPointError(f"non-finite validation {cfg.metric}: {path_losses}")
            losses = self.losses_for(cost, path_losses)
            record(trial, losses=losses)
            if keep:
                artifact = optuna.artifacts.upload_artifact(
                    artifact_store=self.artifacts, file_path=str(ckpt), study_or_trial=trial)
                record(trial, weights_artifact=artifact)
        return self.values(losses, pm, latency)

    def quantized(self, trial, net, path_metrics: list[dict], cost, size: tuple[int, int] | None = None) -> list[dict]:
        """An int8 candidate's metrics: those of its fp32 weights ``net`` (on the frames every trial
        uses, at ``size``: the training size unless given) times what quantizing its graphs does to each
        path, measured with onnxruntime
        (explorer.deploy.quantize); both, and the change, are kept on ``trial``. The graphs quantized are those
        the device profile prices int8 (``CandidateCost.int8_graphs``), as its latency assumes."""
        net.eval()
        graphs = cost.int8_graphs(self.device_profile)
        size = size or net.candidate.frame_size(self.config.train_size)   # the frames its estimate used
        effect = quantization_effect(net, tuple(size), self.config.data,
                                     eval_frames=self.config.val_limit or 32, stages=graphs)
        record(trial, int8_graphs=list(graphs), path_metrics_fp32=path_metrics,
               quantization=json_safe({k: effect[k] for k in ("rmse_degradation", "frames")}))
        return [{k: v * r.get(k, 1.0) if isinstance(v, (int, float)) else v for k, v in m.items()}
                for m, r in zip(path_metrics, effect["ratios"])]

    def _rejection(self, pm, latency) -> str:
        cfg = self.config
        if cfg.max_params is not None and pm[-1][0] > cfg.max_params:
            return f"{pm[-1][0] / 1e6:.3f}M parameters > --max-params {cfg.max_params / 1e6:g}M"
        if cfg.max_first_exit_ms is not None and len(latency) > 1 and latency[1] > cfg.max_first_exit_ms:
            return f"first exit at {latency[1]:.2f} ms > --max-first-exit {cfg.max_first_exit_ms:g}ms"
        return ""
