"""The report's figures, each a PNG as base64 text for embedding: anytime step curves, the winner's
paths on a time axis, Pareto fronts, Optuna's history and importances, depth maps of every path, and a
measured curve beside its prediction."""

from __future__ import annotations

import base64
import io
import math
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
from explorer.study.records import trial_record  # noqa: E402
from explorer.study.results import (  # noqa: E402
    baseline_label,
    figures_kind,
    trial_anytime_loss,
    trial_losses,
    trial_network,
    trial_path_costs,
    trial_precision,
)
from explorer.study.view import StudyView  # noqa: E402

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


def error_name(trial: optuna.trial.FrozenTrial) -> str:
    """What a trial's figures give as each path's error: "RMSE (m)", or "photometric error" for a
    study on frames without depth."""
    return "RMSE (m)" if trial_record(trial).error_metric == "rmse" else "photometric error"


def step_curves(rows, device: DeviceProfile, budget: str, envelope=None) -> str:
    """Each (label, trial, colour) row's anytime curve on ``device`` under ``budget``, over the
    ``envelope`` of dedicated networks (explorer.study.envelope.Envelope) where given."""
    dist = parse_budget(budget)
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    if envelope is not None:
        xs, ys = envelope.curve(dist.upper)
        ax.fill_between(xs, ys, step="post", color="#cbd5e1", alpha=0.5, lw=0)
        n = len(envelope.networks)   # drawn over the curves (dashed): a baseline's line does not hide it
        ax.step(xs, ys, where="post", color=ENVELOPE_COLOUR, lw=1.2, ls="--", zorder=5,
                label=f"envelope of {n} dedicated network{'s' if n != 1 else ''}: L = {envelope.loss:.3f}")
    for label, trial, line_colour in rows:
        if trial_precision(trial) not in device.precisions:
            continue   # an int8 design on a profile without int8 rates: no curve to draw
        costs = trial_path_costs(trial, device, dist.kind)
        xs, ys = anytime_curve(costs, trial_losses(trial), dist.upper)
        loss = trial_anytime_loss(trial, device, dist)
        ax.step(xs, ys, where="post", label=f"{label}: L = {loss:.3f}", color=line_colour, lw=2)
    ax.set_xlim(0, dist.upper)
    ax.set_xlabel(f"budget ({dist.unit}) on {device.name}")
    ax.set_ylabel(f"{error_name(rows[0][1]) if rows else 'RMSE (m)'} of the returned depth map")
    ax.set_title(f"anytime curves, {dist.spec} (area / B_max = anytime loss)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return png(fig)


#: how the report's table of all trials tags a network ``explorer envelope`` retrained (explorer.report.html)
ENVELOPE_TAG = "envelope network"
ENVELOPE_COLOUR = "#64748b"


def _kinds(frame: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """The completed trials of ``frame`` by what they are: the search's candidates (estimates), the
    finalists (measured), the baselines, and the envelope's dedicated networks (each trained for one
    path alone: its anytime loss is no candidate's, and no front is made of it)."""
    done = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
    tag = done["figures"].astype(str)
    envelope = tag.str.startswith(ENVELOPE_TAG)
    plain = (done["baseline"] == "") & ~envelope
    measured = tag.str.startswith("measured")
    return {"estimates": done[plain & ~measured], "finalists": done[plain & measured],
            "baselines": done[(done["baseline"] != "") & ~envelope], "envelope": done[envelope]}


def _draw_apart(ax, kinds: dict[str, pd.DataFrame], xcol: str) -> list[str]:
    """Finalists, baselines (measured or estimated, each its own mark) and envelope networks on ``ax``,
    each series its own mark and legend entry, filled where measured and open where estimated
    (``MARKS``); envelope networks above everything else are drawn at the top edge so that they do not
    squash the candidates. Returns what the legend says, with counts."""
    said = []
    finalists = kinds["finalists"]
    if not finalists.empty:
        ax.scatter(finalists[xcol], finalists["value"], marker="D", s=36, color="#111111", zorder=4,
                   label="finalists (measured)")
        said.append(f"{len(finalists)} finalists (measured)")
    for _, r in kinds["baselines"].iterrows():
        kind = "measured" if str(r["figures"]).startswith("measured") else "estimate"
        ink = colour(r["baseline"])   # an estimate: the outline of a thick cross
        ax.scatter([r[xcol]], [r["value"]], marker="*" if kind == "measured" else "X",
                   s=120 if kind == "measured" else 60, edgecolors=ink, linewidths=1.2,
                   facecolors=ink if kind == "measured" else "none",
                   label=f"{baseline_label(r['baseline'])} ({kind})", zorder=3)
        said.append(f"{baseline_label(r['baseline'])} ({kind})")
    env = kinds["envelope"]
    if env.empty:
        return said
    others = pd.concat([k["value"] for name, k in kinds.items() if name != "envelope"])
    top = np.inf
    if not others.empty:
        low, high = min(float(others.min()), float(env["value"].min())), float(others.max())
        pad = 0.08 * (high - low) or 0.05 * abs(high) or 0.05
        top = high + pad
        if (env["value"] > top).any():
            ax.set_ylim(low - pad, top)
    label = "envelope networks (measured, one path each)"
    inside, above = env[env["value"] <= top], env[env["value"] > top]
    ax.scatter(inside[xcol], inside["value"], marker="v", s=44, color=ENVELOPE_COLOUR, zorder=3, label=label)
    said.append(f"{len(env)} {label}")
    if not above.empty:
        ax.scatter(above[xcol], [top] * len(above), marker="^", s=44, color=ENVELOPE_COLOUR, zorder=3,
                   clip_on=False, label="envelope networks above the axis, at its top")
        said[-1] += f", {len(above)} of them above the axis and drawn at its top"
    return said


#: how the front and the history tell estimates from measurements besides their legend (their captions say it too)
MARKS = "filled marks: measured on retrained networks; open marks (rings, crosses): the search's estimates"


def _estimates(ax, x, y) -> None:
    """The search's estimates: open grey rings."""
    ax.scatter(x, y, s=20, facecolors="none", edgecolors="#8a8a8a", linewidths=0.9, label="trials (estimates)")


def _legend(ax) -> None:
    """The legend below the axes, where it hides no point."""
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles))
    ax.legend(unique.values(), unique.keys(), fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2)


def pareto(frame: pd.DataFrame, xcol: str, xlabel: str) -> tuple[str, str]:
    """The search's estimates of anytime loss against ``xcol`` and their front (of the candidates'
    estimates only); apart from them, each on its own mark, what was measured on retrained networks
    (finalists, baselines), the baselines' estimates and the envelope's networks. Returns the PNG and
    what it shows, for its alt text."""
    fig, ax = plt.subplots(figsize=(5.2, 3.6))
    kinds = _kinds(frame)
    cand = kinds["estimates"]
    _estimates(ax, cand[xcol], cand["value"])
    front, best = [], np.inf
    for _, r in cand.sort_values(xcol).iterrows():
        if r["value"] < best:
            best = r["value"]
            front.append((r[xcol], r["value"]))
    said = [f"{len(cand)} trials (estimates)"]
    if front:
        fx, fy = zip(*front)
        ax.step(fx, fy, where="post", color="#d62728", lw=1.5, label="front of the estimates")
        said.append(f"the front of the estimates ({len(front)} points)")
    said += _draw_apart(ax, kinds, xcol)
    ax.set_xscale("log")
    # a space spans less than a decade of MACs: ticks at 1, 2 and 5 of each decade, in engineering units
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.EngFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel("anytime loss")
    ax.grid(alpha=0.3)
    _legend(ax)
    return png(fig), f"Anytime loss against {xlabel}: " + "; ".join(said) + f" ({MARKS})"


def history(frame: pd.DataFrame) -> tuple[str, str]:
    """Every completed trial's anytime loss by trial number: the search's estimates and the best of them
    so far; apart, each on its own mark, finalists, baselines and envelope networks (which come after
    the search and are no candidates). Returns the PNG and what it shows, for its alt text."""
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    kinds = _kinds(frame)
    cand = kinds["estimates"].sort_values("number")
    _estimates(ax, cand["number"], cand["value"])
    said = [f"{len(cand)} trials (estimates)"]
    if not cand.empty:
        ax.step(cand["number"], cand["value"].cummin(), where="post", color="#d62728", lw=1.5,
                label="best estimate so far")
        said.append("the best estimate so far")
    said += _draw_apart(ax, kinds, "number")
    ax.set_xlabel("trial")
    ax.set_ylabel("anytime loss")
    ax.set_title("optimisation history")
    ax.grid(alpha=0.3)
    _legend(ax)
    return png(fig), "Anytime loss by trial: " + "; ".join(said) + f" ({MARKS})"


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


def worse_than_earlier(errors) -> dict[int, int]:
    """The paths ordered badly: {path: the earlier path with a lower error}. A budget that reaches such a
    path returns a worse map than one that stopped before it."""
    out, best = {}, 0
    for i in range(1, len(errors)):
        if errors[i] > errors[best]:
            out[i] = best
        elif errors[i] < errors[best]:
            best = i
    return out


def path_timeline(trial: optuna.trial.FrozenTrial, device: DeviceProfile, budget: str) -> tuple[str | None, dict]:
    """A trial's paths on a time axis: a bar per path from 0 to when its output is ready on ``device``
    (the cost model's estimate, as in the path table), its RMSE on the right, the end of ``budget``'s
    range marked, and the paths worse than an earlier one in red. (PNG, worse_than_earlier), or (None,
    {}) where ``device`` cannot price the trial's precision."""
    costs = trial_path_costs(trial, device, "time")
    if any(math.isnan(c) for c in costs):
        return None, {}
    errors, dist = trial_losses(trial), parse_budget(budget)
    worse = worse_than_earlier(errors)
    # Optuna's plots switch the global style to ggplot: this one keeps its own look whatever ran before
    with plt.style.context("default"):
        fig, ax = plt.subplots(figsize=(4.6, 0.45 * len(errors) + 1.4))
        _draw_paths(ax, costs, errors, worse, dist)
        ax.set_xlabel(f"ms until the path's output is ready\n(estimated on {device.name})", fontsize=11)
        rmse = ax.twinx()
        rmse.set_ylim(ax.get_ylim())
        unit = " m" if trial_record(trial).error_metric == "rmse" else ""
        rmse.set_yticks(range(len(errors)), [f"{e:.3g}{unit}" for e in errors], fontsize=11)
        for i, label in enumerate(rmse.get_yticklabels()):
            label.set_color("#b91c1c" if i in worse else "#111111")
        rmse.set_ylabel(f"{error_name(trial)}, {figures_kind(trial)}", fontsize=11)
        return png(fig), worse


def _draw_paths(ax, costs: list[float], errors: list[float], worse: dict, dist) -> None:
    """The bars of :func:`path_timeline`, the budget's end and the region past it."""
    n, right = len(errors), max(max(costs), dist.upper) * 1.06
    ax.axvspan(dist.upper, right, color="#e5e7eb", lw=0)
    for i, c in enumerate(costs):
        bad = i in worse
        ax.barh(i, c, height=0.6, color="#fca5a5" if bad else "#93c5fd", edgecolor="#b91c1c" if bad else "#1f77b4",
                hatch="//" if bad else None, lw=1)
        ax.plot([c], [i], "o", ms=5, color="#b91c1c" if bad else "#1f77b4", clip_on=False)
        if bad:   # inside a long bar, beside a short one
            inside = c > 0.55 * right
            ax.text(c - 0.02 * right if inside else c + 0.03 * right, i, f"worse than path {worse[i]}",
                    ha="right" if inside else "left", va="center", fontsize=10, color="#7f1d1d",
                    bbox=dict(facecolor="white", edgecolor="none", pad=1, alpha=0.85))
    mark = f"B_max {dist.upper:g} ms" if dist.name == "uniform" else f"{dist.spec}: almost all by {dist.upper:g} ms"
    ax.axvline(dist.upper, color="#111111", ls="--", lw=1.2, label=mark)
    ax.set_xlim(0, right)
    ax.set_ylim(n - 0.5, -0.5)        # path 0 on top, as in the table
    ax.set_yticks(range(n), ["path 0 (scan)"] + [f"path {i}" for i in range(1, n)], fontsize=11)
    ax.tick_params(axis="x", labelsize=11)
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=10, frameon=False)


def depth_map_size(view: StudyView, trial: optuna.trial.FrozenTrial) -> tuple[int, int]:
    """The input size a trial's figures hold at: a retrained network's deployment size (where it was
    measured, and runs as shipped), else the study's training size (where the search estimated it)."""
    measured = trial_record(trial).measured
    return tuple(measured.input_size) if measured else tuple(view.config.train_size)


def depth_maps(view: StudyView, trial: optuna.trial.FrozenTrial, data: str | None,
               device: DeviceProfile | None = None, count: int = 3):
    """Every path's depth map on a few validation images at :func:`depth_map_size` (needs the trial's
    stored weights), each path's column titled with its time on ``device`` and its RMSE: (PNG, "") or
    (None, why not)."""
    import torch
    try:
        net = trial_network(view, trial)
    except UserError as exc:
        return None, str(exc)
    try:
        ds = open_dataset(data or view.config.data, "val", depth_map_size(view, trial),
                          train_augment=False)
    except UserError as exc:
        return None, str(exc)
    items = [ds[i] for i in range(min(count, len(ds)))]
    if not items:
        return None, "the data set has no validation frames"
    with torch.no_grad():
        outs = [net(item["image"][None], item["scan"][None], item["scan_row"]) for item in items]
    legend = ((f"ms: estimated on {device.name}\n" if device is not None else "")
              + f"{'m: RMSE' if trial_record(trial).error_metric == 'rmse' else 'photometric error'}, {figures_kind(trial)}")
    return png(_map_grid(items, outs, _path_titles(trial, net.candidate.num_paths, device), legend)), ""


def _path_titles(trial: optuna.trial.FrozenTrial, paths: int, device: DeviceProfile | None) -> list[str]:
    """A column title per path, in short lines that stay legible on a phone: its name, its time on
    ``device`` (where it prices the trial) and its RMSE."""
    costs = trial_path_costs(trial, device, "time") if device is not None else []
    errors = trial_losses(trial)
    titles = []
    for p in range(paths):
        lines = [f"path {p}"]
        if p < len(costs) and not math.isnan(costs[p]):
            lines.append(f"{costs[p]:.3g} ms")
        if p < len(errors):
            lines.append(f"{errors[p]:.3g}{' m' if trial_record(trial).error_metric == 'rmse' else ''}")
        titles.append("\n".join(lines))
    return titles


def _map_grid(items: list, outs: list, titles: list[str], legend: str):
    """A row per frame (image, ground truth, then every path), one depth scale for all with its colour bar."""
    # one scale for all: the recorded depth's, or the paths' own where the frames have none
    recorded = max(float(item["depth"].max()) for item in items)
    vmax = recorded or max(float(o.max()) for out in outs for o in out)
    cols = len(titles) + 2
    height, width = items[0]["depth"].shape[-2:]
    # the page scales a figure down to the screen: at 1.5 in a column, 16 pt titles stay legible at 390 px
    cell = 1.5
    with plt.style.context("default"):   # whatever style Optuna's plots left behind
        fig, axes = plt.subplots(len(items), cols, figsize=(cell * cols + 0.8, cell * height / width * len(items) + 1.4),
                                 squeeze=False, layout="constrained")
        for i, (item, out) in enumerate(zip(items, outs)):
            axes[i, 0].imshow(item["image"].permute(1, 2, 0).numpy())
            shown = axes[i, 1].imshow(item["depth"][0].numpy(), cmap="viridis", vmin=0, vmax=vmax)
            for p, o in enumerate(out):
                axes[i, p + 2].imshow(o[0, 0].numpy(), cmap="viridis", vmin=0, vmax=vmax)
        for j, title in enumerate(["image", "ground\ntruth" if recorded else "no depth\nrecorded"] + titles):
            axes[0, j].set_title(title, fontsize=16)
        for ax in axes.flat:
            ax.axis("off")
        fig.suptitle(legend, fontsize=16)
        bar = fig.colorbar(shown, ax=axes, fraction=0.04, aspect=30)
        bar.set_label("depth (m)", fontsize=16)
        bar.ax.tick_params(labelsize=14)
    return fig


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
