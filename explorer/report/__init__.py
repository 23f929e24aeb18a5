"""The HTML report of a study: one self-contained file (figures embedded as PNG, no network access)
with the summary, the best candidate (Table 1 style), anytime losses against the baselines (Table 2
style), step curves (Figure 5), the Pareto front, the optimisation history, parameter importances,
depth maps of every path (Figure 4), and a sortable table of all trials."""

from __future__ import annotations

import base64
import io
import platform
import time
import warnings
from pathlib import Path
from typing import Sequence

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import optuna  # noqa: E402
import pandas as pd  # noqa: E402
from jinja2 import Environment, FileSystemLoader, select_autoescape  # noqa: E402

from explorer import __version__  # noqa: E402
from explorer.anytime import anytime_curve, parse_budget  # noqa: E402
from explorer.cost.devices import DeviceProfile, get_device  # noqa: E402
from explorer.errors import UserError  # noqa: E402
from explorer.study.results import (baseline_label, baseline_trial, finalists_frame,  # noqa: E402
                              is_retrained, missing_baselines, path_table, scored_trials, study_baselines,
                              trial_anytime_loss,
                              trial_losses, trial_path_costs, trial_precision, trials_frame, winner)
from explorer.space import Candidate  # noqa: E402

TABLE2_BUDGETS = ("time:uniform:100ms", "time:uniform:50ms", "time:uniform:33ms",
                  "energy:uniform:0.5J", "energy:uniform:0.25J")
COLOURS = {"best": "#d62728", "paper": "#1f77b4", "paper-nee": "#7f7f7f", "fastdepth": "#2ca02c"}

#: reference networks a study compares against: one colour each, by their place in REFERENCES
OTHER_COLOURS = ("#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf", "#ff7f0e")


def _colour(baseline: str) -> str:
    if baseline in COLOURS:
        return COLOURS[baseline]
    from explorer.model.reference import REFERENCES
    names = list(REFERENCES)
    return OTHER_COLOURS[names.index(baseline) % len(OTHER_COLOURS)] if baseline in names else "k"


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def _label(t: optuna.trial.FrozenTrial, best: optuna.trial.FrozenTrial | None) -> str:
    b = t.user_attrs.get("baseline")
    if b:
        return baseline_label(b)
    return f"best (trial {t.number})" if best is not None and t.number == best.number else f"trial {t.number}"


def _budget_label(dist) -> str:
    """The paper's notation for uniform budgets (L_T@33ms, L_E@0.5J), the spec otherwise."""
    if dist.name == "uniform":
        return f"L_{'T' if dist.kind == 'time' else 'E'}@{dist.maximum:g}{dist.unit}"
    return dist.spec


def _step_curves(rows, device: DeviceProfile, budget: str) -> str:
    dist = parse_budget(budget)
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for label, trial, colour in rows:
        if trial_precision(trial) not in device.precisions:
            continue   # an int8 design on a profile without int8 rates: no curve to draw
        costs = trial_path_costs(trial, device, dist.kind)
        xs, ys = anytime_curve(costs, trial_losses(trial), dist.upper)
        loss = trial_anytime_loss(trial, device, dist)
        ax.step(xs, ys, where="post", label=f"{label}: L = {loss:.3f}", color=colour, lw=2)
    ax.set_xlim(0, dist.upper)
    ax.set_xlabel(f"budget ({dist.unit}) on {device.name}")
    ax.set_ylabel("RMSE of the returned depth map (m)")
    ax.set_title(f"anytime curves, {dist.spec} (area / B_max = anytime loss)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig)


def _pareto(frame: pd.DataFrame, xcol: str, xlabel: str) -> str:
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    done = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
    cand = done[done["baseline"] == ""]
    ax.scatter(cand[xcol], cand["value"], s=18, alpha=0.7, label="trials", color="#999999")
    pts = cand.sort_values(xcol)
    front, best = [], np.inf
    for _, r in pts.iterrows():
        if r["value"] < best:
            best = r["value"]
            front.append((r[xcol], r["value"]))
    if front:
        fx, fy = zip(*front)
        ax.step(fx, fy, where="post", color="#d62728", lw=1.5, label="Pareto front")
    for _, r in done[done["baseline"] != ""].iterrows():
        ax.scatter([r[xcol]], [r["value"]], marker="*", s=120, color=_colour(r["baseline"]),
                   label=baseline_label(r["baseline"]), zorder=3)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel("anytime loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _png(fig)


def _optuna_plot(fn, study) -> str | None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ax = fn(study)
        fig = ax.figure if hasattr(ax, "figure") else ax[0].figure
        fig.set_size_inches(6.4, 3.6)
        return _png(fig)
    except Exception:  # too few trials, multi-objective, a constant parameter: leave the figure out
        plt.close("all")
        return None


def _depth_maps(study: optuna.Study, trial: optuna.trial.FrozenTrial, data: str | None, count: int = 3):
    """Every path's depth map on a few validation images (needs the trial's stored weights)."""
    import torch
    from explorer.data import open_dataset
    from explorer.study.results import trial_network
    cfg = study.user_attrs.get("config", {})
    try:
        net = trial_network(study, trial)
    except UserError as exc:
        return None, str(exc)
    size = tuple(cfg.get("train_size", (64, 64)))
    try:
        ds = open_dataset(data or cfg.get("data", "synthetic"), "val", size, train_augment=False)
    except UserError as exc:
        return None, str(exc)
    n = min(count, len(ds))
    paths = net.candidate.num_paths
    fig, axes = plt.subplots(n, paths + 2, figsize=(1.6 * (paths + 2), 1.6 * n), squeeze=False)
    with torch.no_grad():
        for i in range(n):
            item = ds[i]
            outs = net(item["image"][None], item["scan"][None], item["scan_row"])
            vmax = float(item["depth"].max())
            axes[i, 0].imshow(item["image"].permute(1, 2, 0).numpy())
            axes[i, 1].imshow(item["depth"][0].numpy(), cmap="viridis", vmin=0, vmax=vmax)
            for p, o in enumerate(outs):
                axes[i, p + 2].imshow(o[0, 0].numpy(), cmap="viridis", vmin=0, vmax=vmax)
            if i == 0:
                for j, title in enumerate(["image", "ground truth"] + [f"path {p}" for p in range(paths)]):
                    axes[0, j].set_title(title, fontsize=8)
    for ax in axes.flat:
        ax.axis("off")
    return _png(fig), ""


def _versions() -> dict:
    import onnxruntime
    import torch
    return {"anytime-explorer": __version__, "optuna": optuna.__version__, "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__, "python": platform.python_version()}


def _frame_html(frame: pd.DataFrame, table_id: str, fmt: dict | None = None) -> str:
    fmt = fmt or {}
    def f(v, col):
        if isinstance(v, float):
            if np.isnan(v):
                return ""
            return fmt.get(col, "{:.4g}").format(v)
        return v
    shown = frame.copy()
    for c in shown.columns:
        shown[c] = [f(v, c) for v in shown[c]]
    return shown.to_html(index=False, table_id=table_id, classes="sortable", escape=True, border=0)


def build_context(study: optuna.Study, devices: Sequence[str] | None = None,
                  budgets: Sequence[str] | None = None, data: str | None = None) -> dict:
    cfg = study.user_attrs.get("config", {})
    study_device = study.user_attrs.get("device_profile")
    primary = get_device(cfg.get("device", "tx2")) if not study_device else \
        DeviceProfile.from_dict(study_device, "study")
    devs = [primary] + [get_device(d) for d in (devices or ["tx2", "rpi4"]) if d != primary.name]
    budget_list = list(dict.fromkeys(list(cfg.get("budgets", [])) + list(budgets or TABLE2_BUDGETS)))
    dists = [parse_budget(b) for b in budget_list]
    frame = trials_frame(study)
    states = frame["state"].value_counts().to_dict() if not frame.empty else {}
    best = winner(study)
    retrained = best is not None and is_retrained(best)
    scored = scored_trials(study)
    ranked = sorted([t for t in scored if not t.user_attrs.get("baseline") and is_retrained(t) == retrained],
                    key=lambda t: t.values[0])[:3]
    baselines = [t for name in study_baselines(study) if (t := baseline_trial(study, name, retrained=retrained))]
    ctx: dict = {"study": study.study_name, "config": cfg, "states": states, "versions": _versions(),
                 "generated": time.strftime("%Y-%m-%d %H:%M:%S"), "figures": {}, "notes": [],
                 "evaluator": cfg.get("evaluator", "proxy"), "finalist_steps": cfg.get("finalist_steps"),
                 "plan": study.user_attrs.get("plan")}
    from explorer.study.finalists import finalist_trials
    recipes = sorted({t.user_attrs["finalist"]["recipe"]["steps"] for t in finalist_trials(study)})
    if recipes:   # a --time-limit plan may have sized them after the study was created
        ctx["finalist_steps"] = ", ".join(map(str, recipes))
    fin = finalists_frame(study)
    ctx["finalists"], ctx["finalists_tau"] = "", None
    if not fin.empty:
        both = fin.dropna(subset=["estimated"])
        if len(both) >= 3:
            from scipy.stats import kendalltau
            ctx["finalists_tau"] = float(kendalltau(both["estimated"], both["retrained"]).statistic)
        ctx["finalists"] = _frame_html(fin, "finalists-table")
    lacking = [d.name for d in devs if "int8" not in d.precisions]
    if lacking and any(trial_precision(t) == "int8" for t in scored):
        ctx["notes"].append(f"int8 designs are not priced on {', '.join(lacking)}: those profiles have no int8 "
                            "rates, so their cells there are empty.")
    for name, why in (study.user_attrs.get("baselines_not_estimated") or {}).items():
        ctx["notes"].append(f"Baseline {baseline_label(name)} has no search estimate: {why}.")
    starts = [t.datetime_start for t in study.trials if t.datetime_start]
    ends = [t.datetime_complete for t in study.trials if t.datetime_complete]
    ctx["wall_time"] = f"{(max(ends) - min(starts)).total_seconds() / 60:.1f} min" if starts and ends else "n/a"
    ctx["devices"] = [{"name": d.name, "description": d.description, "calibrated": d.calibrated,
                       "fit": d.provenance.get("fit", []), "sources": d.provenance.get("sources", []),
                       "conditions": d.provenance.get("conditions")} for d in devs]
    ctx["budgets"] = [d.spec for d in dists]
    ctx["multi_objective"] = len(study.directions) > 1
    if best is not None:
        cand = Candidate.from_dict(best.user_attrs["candidate"])
        how = "retrained" if retrained else f"estimated by the {(best.user_attrs.get('evaluator') or {}).get('evaluator', 'proxy')} evaluator"
        ctx["best"] = {"number": best.number, "value": best.values[0], "key": cand.key, "how": how,
                       "architecture": cand.describe(), "yaml": cand.to_yaml(),
                       "table": _frame_html(path_table(best, devs), "best-table")}
        paper = baseline_trial(study, "paper", retrained=retrained)
        if paper is not None:
            ctx["best"]["ratio"] = best.values[0] / paper.values[0]
    # a baseline without a row is named, with why (not run, queued, failed, interrupted)
    ctx["missing_baselines"] = missing_baselines(study)
    ctx["no_ratio"] = next((m["why"] for m in ctx["missing_baselines"] if m["name"] == "paper"), "")
    # Table 2: rows = best candidates and baselines, columns = device x budget
    rows = []
    for t in ranked + baselines:
        row = {"model": _label(t, best), "trial": t.number}
        for d in devs:
            for dist in dists:
                if dist.kind == "energy" and d.active_power_w <= 0:
                    continue  # no energy model for this device
                row[f"{d.name} {_budget_label(dist)}"] = trial_anytime_loss(t, d, dist, cfg.get("metric", "rmse"))
        rows.append(row)
    ctx["table2"] = _frame_html(pd.DataFrame(rows), "table2") if rows else ""
    from explorer.cost import reference_table
    ctx["references"] = _frame_html(reference_table(devs), "references")
    curve_rows = []
    if best is not None:
        curve_rows.append((_label(best, best), best, COLOURS["best"]))
    curve_rows += [(_label(t, best), t, _colour(t.user_attrs["baseline"])) for t in baselines]
    if curve_rows:
        ctx["figures"]["curve_time"] = _step_curves(curve_rows, primary, next(
            (d.spec for d in dists if d.kind == "time"), "time:uniform:33ms"))
        energy = next((d.spec for d in dists if d.kind == "energy"), None)
        if energy and primary.active_power_w > 0:
            ctx["figures"]["curve_energy"] = _step_curves(curve_rows, primary, energy)
    if not frame.empty and (frame["state"] == "COMPLETE").any() and not ctx["multi_objective"]:
        ctx["figures"]["pareto_params"] = _pareto(frame, "params", "parameters (last path)")
        ctx["figures"]["pareto_macs"] = _pareto(frame, "macs", "MACs (last path)")
    if not ctx["multi_objective"]:
        from optuna.visualization import matplotlib as ovm
        for name, fn in (("history", ovm.plot_optimization_history), ("importances", ovm.plot_param_importances)):
            png = _optuna_plot(fn, study)
            if png:
                ctx["figures"][name] = png
    if best is not None:
        png, note = _depth_maps(study, best, data)
        if png:
            ctx["figures"]["depth_maps"] = png
        elif note:
            ctx["notes"].append(f"Depth maps left out: {note}.")
    cols = ["number", "state", "value", "baseline", "retry_of", "candidate_key", "params", "macs", "paths",
            "first_exit_ms", "last_exit_ms", "last_rmse", "duration_s", "reason", "architecture"]
    ctx["trials"] = _frame_html(frame[[c for c in cols if c in frame.columns]], "trials") if not frame.empty else ""
    return ctx


def _measured_curve(curve: Path) -> str | None:
    import json
    try:
        res = json.loads(curve.read_text())
        m = res["measured"]
    except (OSError, ValueError, KeyError):
        return None
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    xs, ys = anytime_curve(res["predicted_costs_ms"], res["path_losses"], res["b_max_ms"])
    ax.step(xs, ys, where="post", color="#1f77b4", lw=2,
            label=f"predicted ({res['device']}): L = {res['predicted_anytime_loss']:.4f}")
    ax.plot(m["deadlines_ms"], m["loss"], "o", ms=3, color="#d62728",
            label=f"measured here: L = {res['measured_anytime_loss']:.4f}")
    ax.set_xlabel("deadline (ms) on this machine")
    ax.set_ylabel("RMSE of the returned map (m)")
    ax.set_title(f"exported model {res['candidate_key']}, {res['frames']} frames")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig)


def write_report(study: optuna.Study, out_dir: str | Path, devices: Sequence[str] | None = None,
                 budgets: Sequence[str] | None = None, data: str | None = None,
                 curve: Path | None = None) -> Path:
    """Writes ``out_dir/report.html`` (atomically) and returns its path. ``curve``: a measured
    anytime curve (``explorer curve``) to show next to its prediction."""
    ctx = build_context(study, devices, budgets, data)
    curve = curve or Path(out_dir) / "export" / "anytime_curve.json"
    if curve.is_file():
        png = _measured_curve(curve)
        if png:
            ctx["figures"]["measured_curve"] = png
    env = Environment(loader=FileSystemLoader(Path(__file__).parent), autoescape=select_autoescape(["html", "j2"]))
    html = env.get_template("report.html.j2").render(**ctx)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(html, encoding="utf-8")
    tmp.replace(path)
    return path
