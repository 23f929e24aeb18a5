"""The report's figures, each a PNG as base64 text for embedding: anytime step curves, Pareto fronts,
Optuna's history and importances, depth maps of every path, and a measured curve beside its
prediction."""

from __future__ import annotations

import base64
import io
import warnings
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import optuna  # noqa: E402
import pandas as pd  # noqa: E402

from explorer.anytime import anytime_curve, parse_budget  # noqa: E402
from explorer.cost.devices import DeviceProfile  # noqa: E402
from explorer.data import open_dataset
from explorer.errors import UserError  # noqa: E402
from explorer.model.reference import REFERENCES
from explorer.study.results import (  # noqa: E402
    baseline_label,
    trial_anytime_loss,
    trial_losses,
    trial_network,
    trial_path_costs,
    trial_precision,
)

COLOURS = {"best": "#d62728", "paper": "#1f77b4", "paper-nee": "#7f7f7f", "fastdepth": "#2ca02c"}

#: reference networks a study compares against: one colour each, by their place in REFERENCES
OTHER_COLOURS = ("#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf", "#ff7f0e")


def colour(baseline: str) -> str:
    if baseline in COLOURS:
        return COLOURS[baseline]
    names = list(REFERENCES)
    return OTHER_COLOURS[names.index(baseline) % len(OTHER_COLOURS)] if baseline in names else "k"


def png(fig) -> str:
    """``fig`` as base64 PNG text (and closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def step_curves(rows, device: DeviceProfile, budget: str, envelope=None) -> str:
    """Each (label, trial, colour) row's anytime curve on ``device`` under ``budget``, over the
    ``envelope`` of dedicated networks (explorer.study.envelope.Envelope) where given."""
    dist = parse_budget(budget)
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    if envelope is not None:
        xs, ys = envelope.curve(dist.upper)
        ax.fill_between(xs, ys, step="post", color="#cbd5e1", alpha=0.5, lw=0)
        ax.step(xs, ys, where="post", color="#64748b", lw=1.2, ls="--",
                label=f"envelope of {len(envelope.networks)} dedicated networks: L = {envelope.loss:.3f}")
    for label, trial, line_colour in rows:
        if trial_precision(trial) not in device.precisions:
            continue   # an int8 design on a profile without int8 rates: no curve to draw
        costs = trial_path_costs(trial, device, dist.kind)
        xs, ys = anytime_curve(costs, trial_losses(trial), dist.upper)
        loss = trial_anytime_loss(trial, device, dist)
        ax.step(xs, ys, where="post", label=f"{label}: L = {loss:.3f}", color=line_colour, lw=2)
    ax.set_xlim(0, dist.upper)
    ax.set_xlabel(f"budget ({dist.unit}) on {device.name}")
    ax.set_ylabel("RMSE of the returned depth map (m)")
    ax.set_title(f"anytime curves, {dist.spec} (area / B_max = anytime loss)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return png(fig)


def pareto(frame: pd.DataFrame, xcol: str, xlabel: str) -> str:
    """The search's estimates of anytime loss against ``xcol`` and their front; beside them, told apart
    in the legend, what was measured on retrained networks (finalists, baselines) and the baselines'
    estimates, each labelled once."""
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    done = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
    measured = done["figures"].astype(str).str.startswith("measured")
    cand = done[(done["baseline"] == "") & ~measured]
    ax.scatter(cand[xcol], cand["value"], s=18, alpha=0.7, label="trials (estimates)", color="#999999")
    pts = cand.sort_values(xcol)
    front, best = [], np.inf
    for _, r in pts.iterrows():
        if r["value"] < best:
            best = r["value"]
            front.append((r[xcol], r["value"]))
    if front:
        fx, fy = zip(*front)
        ax.step(fx, fy, where="post", color="#d62728", lw=1.5, label="front of the estimates")
    finalists = done[(done["baseline"] == "") & measured]
    if not finalists.empty:
        ax.scatter(finalists[xcol], finalists["value"], marker="D", s=36, color="#111111", zorder=4,
                   label="finalists (measured)")
    for _, r in done[done["baseline"] != ""].iterrows():
        kind = "measured" if str(r["figures"]).startswith("measured") else "estimate"
        ax.scatter([r[xcol]], [r["value"]], marker="*" if kind == "measured" else "x", s=120 if kind == "measured" else 50,
                   color=colour(r["baseline"]), label=f"{baseline_label(r['baseline'])} ({kind})", zorder=3)
    ax.set_xscale("log")
    # a space spans less than a decade of MACs: ticks at 1, 2 and 5 of each decade, in engineering units
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.EngFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel("anytime loss")
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles))
    ax.legend(unique.values(), unique.keys(), fontsize=7)
    return png(fig)


def optuna_plot(fn, study) -> str | None:
    """One of Optuna's matplotlib plots of ``study``, or None where it cannot draw one."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ax = fn(study)
        fig = ax.figure if hasattr(ax, "figure") else ax[0].figure
        fig.set_size_inches(6.4, 3.6)
        return png(fig)
    except Exception:  # too few trials, multi-objective, a constant parameter: leave the figure out
        plt.close("all")
        return None


def depth_maps(study: optuna.Study, trial: optuna.trial.FrozenTrial, data: str | None, count: int = 3):
    """Every path's depth map on a few validation images (needs the trial's stored weights): (PNG,
    "") or (None, why not)."""
    import torch
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
    return png(fig), ""


def measured_curve(curve: Path) -> str | None:
    """A measured anytime curve (``explorer curve``'s JSON) beside its prediction; None where the
    file cannot be read."""
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
    return png(fig)
