"""Reading a study: trials as a pandas table, per-path costs re-computed from stored workloads, and
re-scoring for another device or budget without training anything again."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import optuna
import pandas as pd

from explorer.anytime import anytime_loss, parse_budget
from explorer.cost.devices import DeviceProfile, check_budget_priced, get_device, path_latencies_ms
from explorer.cost.workloads import Workload
from explorer.data import frames_for_downscale, open_dataset
from explorer.errors import UserError
from explorer.model.reference import REFERENCES
from explorer.model.shipped import shipped_network
from explorer.space import Candidate
from explorer.study.config import DEFAULT_BASELINES
from explorer.study.records import trial_record
from explorer.study.retry import interrupted_trials, retries_by_origin
from explorer.study.storage import load_study
from explorer.study.view import StudyView
from explorer.supernet import load_supernet
from explorer.supernet.evaluators import loaded_batches, recalibrate_batchnorm
from explorer.training.train import network_from_checkpoint

BASELINE_LABELS = {"paper": "paper design", "paper-nee": "paper design, no early exit",
                   "fastdepth": "FastDepth-like"}


def baseline_label(name: str) -> str:
    """How summaries and reports name a baseline (a reference network by its own name)."""
    return BASELINE_LABELS.get(name, name)


def study_baselines(view: StudyView) -> list[str]:
    """The baselines a study was created to compare against (--baselines), in order; for a study made
    with --no-baselines, the default ones (so that summaries can say why they are missing)."""
    chosen = view.config.baselines if view.record.config else DEFAULT_BASELINES
    names = list(chosen or DEFAULT_BASELINES)
    # a resumed run may have been given more (--baselines): they have trials of their own
    tagged = (trial_record(t).baseline for t in view.trials)
    return list(dict.fromkeys(names + [b for b in tagged if b]))


def compact_workloads(cost) -> dict:
    """What re-costing on any profile needs: per layer (stage, kind, MACs, bytes, params, in-channels
    and kernel)."""
    stages = list(dict.fromkeys(w.stage for w in cost.workloads))
    return {"input_size": list(cost.input_size), "stages": stages,
            "path_stages": [[stages.index(s) for s in ps] for ps in cost.path_stages],
            "layers": [[stages.index(w.stage), w.kind, w.macs, w.bytes_read, w.bytes_written, w.params,
                        w.in_shape[0] if w.in_shape else 0, w.kernel] for w in cost.workloads]}


def expand_workloads(compact: dict) -> tuple[list[Workload], list[list[str]]]:
    stages = compact["stages"]
    # rows stored before in-channels and kernel were kept have 6 fields: their shape stays unknown
    wl = [Workload(stages[s], "", kind, tuple(int(c) for c in shape[:1]), (), int(shape[1]) if shape else 0, 0,
                   int(macs), int(params), int(br), int(bw))
          for s, kind, macs, br, bw, params, *shape in compact["layers"]]
    return wl, [[stages[i] for i in ps] for ps in compact["path_stages"]]


def trial_precision(trial: optuna.trial.FrozenTrial) -> str:
    return trial_record(trial).precision


def trial_path_costs(trial: optuna.trial.FrozenTrial, device: DeviceProfile, kind: str) -> list[float]:
    """Per-path cost (path 0 included) of a stored trial on ``device``: ms for time, J for energy;
    NaN where the device cannot price the trial's precision (int8 on a profile without int8 rates)."""
    wl, path_stages = expand_workloads(trial_record(trial).workloads)
    precision = trial_precision(trial)
    if precision not in device.precisions:
        return [0.0] + [math.nan] * len(path_stages)
    ms = [0.0] + path_latencies_ms(device.at_precision(precision), wl, path_stages)
    if kind == "time":
        return ms
    return [float(device.energy_j(t)) for t in ms]


def trial_losses(trial: optuna.trial.FrozenTrial, metric: str | None = None) -> list[float]:
    """Each path's ``metric`` (default: RMSE, or the photometric error where the frames had no depth);
    a NaN among measured paths (an edit), an infinite or a negative error is one line."""
    try:
        losses = trial_record(trial).losses_of(metric)
    except (KeyError, TypeError, ValueError):
        losses = [-1.0]
    measured = [x for x in losses if not math.isnan(x)]
    if not all(0 <= x < math.inf for x in measured) or (measured and len(measured) < len(losses)):
        raise UserError(f"trial {trial.number}'s stored record is damaged (its per-path {metric or 'error'} is "
                        f"not a list of finite errors: {losses}): run the trial again or restore the study's storage")
    return losses


def trial_anytime_loss(trial: optuna.trial.FrozenTrial, device: DeviceProfile, budget,
                       metric: str | None = None) -> float:
    dist = parse_budget(budget)
    if trial_precision(trial) not in device.precisions:
        return math.nan
    return anytime_loss(trial_path_costs(trial, device, dist.kind), trial_losses(trial, metric), dist)


def scored_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    """Completed trials that carry per-path metrics and workloads (everything re-scoring needs); the
    dedicated networks of the envelope (explorer.study.envelope) are a comparison of their own."""
    return [t for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
            if trial_record(t).is_scored and not trial_record(t).is_envelope]


def _reason(t: optuna.trial.FrozenTrial, interrupted: dict[int, str], retries: dict) -> str:
    rec = trial_record(t)
    reason = (rec.rejected or rec.pruned or rec.not_run or interrupted.get(t.number)
              or t.system_attrs.get("fail_reason", "")
              or (f"same candidate as trial {rec.duplicate_of}" if rec.duplicate_of is not None else ""))
    if t.number in interrupted:
        retry = retries.get(t.number)
        reason += f"; tried again as trial {retry.number}" if retry is not None else "; not tried again"
    if rec.retry_of is not None:
        reason = f"retry of trial {rec.retry_of}" + (f"; {reason}" if reason else "")
    return reason


def _reference_description(name: str | None) -> str:
    return REFERENCES[name].description if name in REFERENCES else ""


def trials_frame(study: optuna.Study) -> pd.DataFrame:
    """One row per trial: state, objective value(s), baseline tag, candidate, params, MACs,
    per-path metrics and costs as stored, every recorded budget's anytime loss, and why a trial
    did not complete (rejected, pruned, failed, interrupted and tried again as which trial)."""
    rows = []
    trials = study.get_trials(deepcopy=False)
    interrupted, retries = interrupted_trials(study, trials), retries_by_origin(trials)
    for t in trials:
        rec = trial_record(t)
        latency = rec.latency_ms or []
        row = {"number": t.number, "state": t.state.name,
               "value": (t.values[0] if t.values else np.nan),
               "baseline": rec.baseline or "",
               "figures": rec.figures if t.values else "",
               "evaluator": rec.evaluator_name if rec.evaluator or rec.train else "",
               "candidate_key": rec.candidate_key or "",
               "architecture": (Candidate.from_dict(rec.shipped_candidate).describe() if rec.candidate
                                else _reference_description(rec.reference)),
               "params": (rec.params or [np.nan])[-1],
               "macs": (rec.macs or [np.nan])[-1],
               "paths": len(rec.path_metrics or []) or np.nan,
               "first_exit_ms": latency[1] if len(latency) > 1 else np.nan,
               "last_exit_ms": latency[-1] if latency else np.nan,
               "last_rmse": (rec.path_metrics or [{"rmse": np.nan}])[-1]["rmse"],
               "duration_s": t.duration.total_seconds() if t.duration else np.nan,
               "retry_of": rec.retry_of if rec.retry_of is not None else np.nan,
               "reason": _reason(t, interrupted, retries)}
        if t.values and len(t.values) > 1:
            for i, v in enumerate(t.values):
                row[f"value_{i}"] = v
        for spec, v in (rec.losses or {}).items():
            row[f"L[{spec}]"] = v
        rows.append(row)
    return pd.DataFrame(rows)


def rescore(study: optuna.Study, device: str | DeviceProfile, budgets: Sequence[str],
            metric: str = "rmse") -> pd.DataFrame:
    """Ranks the finished trials for ``device`` and ``budgets`` (sorted by the first budget) from
    what the study stored: no network is built or trained."""
    profile = get_device(device)
    dists = [parse_budget(b) for b in budgets]
    for d in dists:
        check_budget_priced(profile, d)
    rows = []
    for t in scored_trials(study):
        rec = trial_record(t)
        row = {"number": t.number, "baseline": rec.baseline or "", "candidate_key": rec.candidate_key or "",
               "figures": rec.figures}
        for d in dists:
            row[d.spec] = trial_anytime_loss(t, profile, d, metric)
        ms = trial_path_costs(t, profile, "time")
        row["first_exit_ms"] = ms[1] if len(ms) > 1 else np.nan
        row["last_exit_ms"] = ms[-1]
        row["params"] = rec.params[-1]
        rows.append(row)
    frame = pd.DataFrame(rows)
    if frame.empty:
        return frame
    # what was measured ranks before what was estimated; a network appears once, by its best figures
    frame = frame.assign(_estimate=frame["figures"] != "measured")
    frame = frame.sort_values(["_estimate", dists[0].spec], kind="stable")
    frame = frame.drop_duplicates(["candidate_key", "baseline"]).drop(columns="_estimate")
    return frame.reset_index(drop=True)


def figures_kind(trial: optuna.trial.FrozenTrial) -> str:
    """"measured" for a retrained network (finalist or baseline), "estimate" for a search trial."""
    return trial_record(trial).figures


def is_retrained(trial: optuna.trial.FrozenTrial) -> bool:
    """A finalist: retrained stand-alone with the study's longer recipe (see explorer.study.finalists)."""
    return trial_record(trial).is_retrained


def figures_source(trial: optuna.trial.FrozenTrial, train_size: tuple[int, int]) -> str:
    """Where a trial's per-path figures come from, in words: measured on a retrained network at the
    deployment size (on which frames), or estimated by the search at its ``train_size``."""
    rec = trial_record(trial)
    if rec.measured:
        size = "x".join(map(str, rec.measured.input_size))
        return (f"Per-path figures measured on the retrained network at {size}, the deployment size, on the first "
                f"{rec.measured.frames} validation frames of {rec.measured.data}")
    size = "x".join(map(str, train_size))
    how = rec.evaluator_name
    return f"Per-path figures estimated by the search ({how}) at {size}, not at the deployment size"


def best_trial(study: optuna.Study, baseline: bool = False) -> optuna.trial.FrozenTrial | None:
    """The search's lowest estimate among scored trials (baselines excluded unless ``baseline``;
    retrained finalists excluded: see :func:`winner`)."""
    pool = [t for t in scored_trials(study) if (baseline or not trial_record(t).baseline) and not is_retrained(t)]
    return min(pool, key=lambda t: t.values[0], default=None)


def winner(study: optuna.Study) -> optuna.trial.FrozenTrial | None:
    """The study's answer: the best retrained finalist, or the best estimate while none is retrained."""
    retrained = [t for t in scored_trials(study) if is_retrained(t) and not trial_record(t).baseline]
    return min(retrained, key=lambda t: t.values[0], default=None) or best_trial(study)


def unbeaten_baseline(study: optuna.Study) -> optuna.trial.FrozenTrial | None:
    """The best retrained baseline when no retrained candidate beats it, else None. Then the best model
    the study found is that baseline, whatever the search estimated: the summary and the report say so
    instead of calling the searched candidate a winner."""
    best = winner(study)
    baselines = [t for t in scored_trials(study) if is_retrained(t) and trial_record(t).baseline]
    base = min(baselines, key=lambda t: t.values[0], default=None)
    if best is None or base is None or not is_retrained(best):
        return None
    return base if base.values[0] <= best.values[0] else None


def baseline_trial(study: optuna.Study, name: str, retrained: bool = False) -> optuna.trial.FrozenTrial | None:
    """Baseline ``name``'s trial: its search estimate, or its retraining with ``retrained``."""
    return next((t for t in scored_trials(study) if trial_record(t).baseline == name
                 and is_retrained(t) == retrained), None)


def finalists_frame(study: optuna.Study) -> pd.DataFrame:
    """Per retrained finalist and baseline: the search's estimate beside the retrained anytime loss,
    with both ranks (how far the estimate can be trusted)."""
    rows = []
    for t in scored_trials(study):
        if not is_retrained(t):
            continue
        rec = trial_record(t)
        rows.append({"model": baseline_label(rec.baseline) if rec.baseline else "finalist",
                     "candidate_key": rec.candidate_key, "estimate_trial": rec.finalist.estimate_trial,
                     "estimated": rec.finalist.estimated, "retrained": t.values[0], "trial": t.number})
    frame = pd.DataFrame(rows)
    if frame.empty:
        return frame
    frame = frame.sort_values("retrained", kind="stable").reset_index(drop=True)
    frame["retrained_rank"] = range(1, len(frame) + 1)
    frame["estimated_rank"] = frame["estimated"].rank(method="min").astype("Int64")
    return frame


def finalists_agreement(study: optuna.Study) -> dict | None:
    """The finalists' agreement: Kendall tau between the search's estimate and the retrained anytime loss
    over the retrained finalists and baselines that have both, {"tau", "rows"}; None under three rows.
    The estimate chose these rows itself (its best of each image encoder), so the figure is no measure
    of how it ranks the rest of the space: :func:`estimate_fidelity` quotes that where it was measured."""
    fin = finalists_frame(study)
    both = fin.dropna(subset=["estimated"]) if not fin.empty else fin
    if len(both) < 3:
        return None
    from scipy.stats import kendalltau
    return {"tau": float(kendalltau(both["estimated"], both["retrained"]).statistic), "rows": len(both)}


def estimate_fidelity(view: StudyView) -> str | None:
    """A sentence on how well the study's supernet ranks its space, as the fidelity benchmark measured
    supernets of the same space, data and recipe (or that none was measured); None for a study that
    did not estimate with a supernet."""
    from explorer.supernet import SupernetRecipe, describe_fidelity, measured_fidelity, read_supernet
    if not view.record.config:
        return None
    config = view.config
    if config.evaluator != "supernet":
        return None
    recipe = config.supernet_recipe()
    try:
        if config.supernet:    # a given file: the recipe it was trained with
            recipe = SupernetRecipe.from_dict(read_supernet(config.supernet)["recipe"])
    except UserError:
        return None
    return describe_fidelity(measured_fidelity(view.context.space, config.data, recipe))


def missing_baselines(view: StudyView) -> list[dict]:
    """The baselines that have no scored trial, each as {"name", "label", "why"}, "why" saying what
    happened to it: not run (--no-baselines, or not yet: queued), still running, failed (its reason),
    interrupted and not tried again. Summaries and reports print these instead of dropping a row."""
    study, trials, stored = view.study, list(view.trials), view.record
    scored = {trial_record(t).baseline for t in scored_trials(study)}
    interrupted = interrupted_trials(study, trials)
    with_baselines = bool(view.config.baselines) if stored.config else True
    why_untrained = ("not retrained: the time limit came first (run the search again with a longer "
                     "--time-limit: it resumes and retrains it)" if stored.plan is not None and stored.plan.not_retrained
                     else "not retrained yet (--finalists 0, or the study has not ended)")
    out = []
    for name in study_baselines(view):
        label = baseline_label(name)
        if name in scored:
            continue
        tagged = [t for t in trials if trial_record(t).baseline == name]
        if not tagged:
            skipped = stored.baselines_not_estimated.get(name)
            why = ("not run: the study was created with --no-baselines" if not with_baselines
                   else f"not estimated: {skipped}; {why_untrained}" if skipped
                   else "not run: it is not in this study")
            out.append({"name": name, "label": label, "why": why})
            continue
        t = tagged[-1]  # the latest attempt
        rec, state = trial_record(t), t.state
        earlier = f" (trial {rec.retry_of} was {interrupted.get(rec.retry_of, 'interrupted')})" \
            if rec.retry_of is not None else ""
        if state == optuna.trial.TrialState.WAITING:
            why = f"not run yet: queued as trial {t.number}{earlier}; run the search longer"
        elif state == optuna.trial.TrialState.RUNNING:
            why = (f"still running as trial {t.number}{earlier}, or its process was killed: resume the "
                   "search to try it again")
        elif t.number in interrupted:
            attempts = len(t.system_attrs.get("retry_history", [])) + 1
            why = (f"trial {t.number} was {interrupted[t.number]} and was not tried again ({attempts} "
                   f"interrupted attempt(s)); resume the search with --max-retries {attempts} or more")
        elif state == optuna.trial.TrialState.FAIL:
            why = f"failed in trial {t.number}: {t.system_attrs.get('fail_reason') or 'no reason recorded'}"
        elif state == optuna.trial.TrialState.PRUNED:
            why = f"pruned in trial {t.number}: {rec.pruned or rec.not_run or rec.rejected or 'no reason recorded'}"
        else:
            why = f"trial {t.number} finished without per-path metrics"
        out.append({"name": name, "label": label, "why": why})
    return out


def path_table(trial: optuna.trial.FrozenTrial, devices: Sequence[DeviceProfile] = ()) -> pd.DataFrame:
    """Table 1 of the paper for one trial: per path, cost per device, RMSE, REL, delta1 (where the frames
    had depth), the photometric error (where they had the camera's motion), params, MACs."""
    rec = trial_record(trial)
    metrics = rec.path_metrics
    frame = pd.DataFrame({"path": range(len(metrics))})
    for dev in devices:
        frame[f"{dev.name} ms"] = trial_path_costs(trial, dev, "time")
        if dev.active_power_w > 0:
            frame[f"{dev.name} J"] = trial_path_costs(trial, dev, "energy")
    for m in ("rmse", "rel", "delta1", "photometric"):
        values = [pm.get(m, np.nan) for pm in metrics]
        if any(v is not None and np.isfinite(v) for v in values):
            frame[m] = values
    frame["params"] = rec.params
    frame["macs"] = rec.macs
    return frame


def study_frame(study: str, storage: str | None = None, reports: str = "reports") -> pd.DataFrame:
    """One call for notebooks: a stored study's trials as a table (see :func:`trials_frame`); the
    study object itself is in ``frame.attrs['study']``."""
    from pathlib import Path
    s = load_study(study, storage, Path(reports))
    frame = trials_frame(s)
    frame.attrs["study"] = s
    return frame


def trial_network(view: StudyView, trial: optuna.trial.FrozenTrial):
    """The network of a trial as it ships (its exits dropped for shipping left out, explorer.model.shipped),
    with its trained weights from the study's artifact store (raises UserError when its weights are not
    stored on this machine)."""
    net = _trained_network(view, trial)
    shipped = trial_record(trial).shipped
    return net if shipped is None else shipped_network(net, Candidate.from_dict(shipped.candidate))


def _trained_network(view: StudyView, trial: optuna.trial.FrozenTrial):
    from pathlib import Path

    from optuna.artifacts import FileSystemArtifactStore, download_artifact

    from explorer.files import scratch_dir
    rec = trial_record(trial)
    if rec.reference:
        raise UserError(f"trial {trial.number} is the reference network {rec.reference}, a baseline "
                        "for comparison: export a candidate's trial")
    artifact, root = rec.weights_artifact, view.record.artifacts_dir
    if not artifact and rec.evaluator_name == "supernet":
        return _supernet_network(view, trial)
    if not artifact or not root or not Path(root).is_dir():
        raise UserError(f"trial {trial.number} has no stored weights here (searched with --no-weights, or its "
                        "artifacts live on another machine): train it with `explorer train` and use the checkpoint")
    with scratch_dir("weights") as tmp:
        f = Path(tmp) / "w.pt"
        try:
            download_artifact(artifact_store=FileSystemArtifactStore(root), file_path=str(f), artifact_id=artifact)
        except Exception as exc:  # a missing or damaged artifact file
            raise UserError(f"trial {trial.number}: its weights could not be read ({exc})") from None
        net, _ = network_from_checkpoint(f)
    return net


def _supernet_network(view: StudyView, trial: optuna.trial.FrozenTrial):
    """A supernet-estimated trial's network: its slice of the supernet, BatchNorm recalibrated on
    the study's training data, exactly as the search evaluated it."""
    from pathlib import Path
    rec = trial_record(trial)
    file = Path(rec.evaluator["supernet"])
    if not file.is_file():
        raise UserError(f"trial {trial.number} was estimated with supernet {file}, which is not on this machine: "
                        "export a retrained finalist instead (the default)")
    # a supernet a time limit stopped short is the one the search estimated with: its slice is the network
    net, state = load_supernet(file, require_complete=False)
    step = rec.evaluator.get("supernet_step")
    if step is not None and state["step"] != step:
        raise UserError(f"trial {trial.number} was estimated with supernet {file} at step {step}, which has trained "
                        f"on since (step {state['step']}): its slice is no longer the network the search scored; "
                        "retrain the candidate (`explorer train`) and export its checkpoint")
    cfg = view.config
    candidate = Candidate.from_dict(rec.candidate)
    calibration = frames_for_downscale(open_dataset(cfg.data, "train", cfg.train_size, train_augment=False),
                                       candidate.downscale)
    sub = net.extract(candidate)
    recalibrate_batchnorm(sub, loaded_batches(calibration, 64, 32))
    return sub


def wall_time(view: StudyView) -> str:
    """The runs' wall time as each search recorded it, the last run's phases beside it (data,
    measuring, supernet, sampling, finalists), or, for a study made before runs were recorded, the
    span of its trials, said so."""
    runs = view.record.runs
    if runs:
        total = sum(r["seconds"] for r in runs) / 60
        phases = runs[-1].get("phases") or {}
        parts = ", ".join(f"{name} {seconds / 60:.1f}" for name, seconds in phases.items())
        return (f"{total:.1f} min" + (f" over {len(runs)} runs" if len(runs) > 1 else "")
                + (f" ({'the last: ' if len(runs) > 1 else ''}{parts} min)" if parts else ""))
    starts = [t.datetime_start for t in view.trials if t.datetime_start]
    ends = [t.datetime_complete for t in view.trials if t.datetime_complete]
    return (f"{(max(ends) - min(starts)).total_seconds() / 60:.1f} min from the first trial to the last (the "
            "supernet's training before them not counted)") if starts and ends else "n/a"
