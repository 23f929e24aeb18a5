"""The report's page: what the template shows (``build_context``: tables, figures, notes) and the
self-contained HTML file written from it (``write_report``)."""

from __future__ import annotations

import platform
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import optuna
import pandas as pd
from jinja2 import Environment, FileSystemLoader, select_autoescape

from explorer import __version__
from explorer.anytime import parse_budget
from explorer.cost import reference_table
from explorer.cost.devices import DeviceProfile
from explorer.cost.fit_errors import fit_errors, fit_words
from explorer.files import write_atomically
from explorer.report import figures
from explorer.model.shipped import DroppedExit
from explorer.space import Candidate
from explorer.study.config import DEFAULT_BUDGET
from explorer.study.envelope import dedicated_path, envelope, envelope_hint, envelope_trials
from explorer.study.finalists import finalist_trials
from explorer.study.records import StudyRecord, trial_record
from explorer.study.results import (
    baseline_label,
    baseline_trial,
    estimate_fidelity,
    figures_kind,
    figures_source,
    finalists_agreement,
    finalists_frame,
    is_retrained,
    missing_baselines,
    path_table,
    scored_trials,
    study_baselines,
    trial_anytime_loss,
    trial_precision,
    trials_frame,
    unbeaten_baseline,
    wall_time,
    winner,
)
from explorer.study.view import StudyView

TABLE2_BUDGETS = ("time:uniform:100ms", "time:uniform:50ms", "time:uniform:33ms",
                  "energy:uniform:0.5J", "energy:uniform:0.25J")

#: the columns of the table of all trials, in order (those the frame has)
TRIAL_COLUMNS = ["number", "state", "value", "figures", "baseline", "retry_of", "candidate_key", "params", "macs", "paths",
                 "first_exit_ms", "last_exit_ms", "last_rmse", "duration_s", "reason", "architecture"]


def _label(t: optuna.trial.FrozenTrial, best: optuna.trial.FrozenTrial | None) -> str:
    b = trial_record(t).baseline
    if b:
        return baseline_label(b)
    return f"best (trial {t.number})" if best is not None and t.number == best.number else f"trial {t.number}"


def _budget_label(dist) -> str:
    """The paper's notation for uniform budgets (L_T@33ms, L_E@0.5J), the spec otherwise."""
    if dist.name == "uniform":
        return f"L_{'T' if dist.kind == 'time' else 'E'}@{dist.maximum:g}{dist.unit}"
    return dist.spec


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


def build_context(view: StudyView, devices: Sequence[str] | None = None,
                  budgets: Sequence[str] | None = None, data: str | None = None,
                  storage_url: str | None = None) -> dict:
    """Everything the report's template shows of the study ``view`` reads: on the study's device first,
    then ``devices`` (default: the comparison devices); under the study's budgets, then ``budgets``
    (default: the paper's Table 2 ones). ``storage_url``: where the study is, for the commands the
    report suggests."""
    study, stored, config = view.study, view.record, view.config
    cfg = stored.config or {}
    devs = view.devices(devices)
    primary = devs[0]
    budget_list = list(dict.fromkeys(list(cfg.get("budgets", [])) + list(budgets or TABLE2_BUDGETS)))
    dists = [parse_budget(b) for b in budget_list]
    frame = _tag_envelope(trials_frame(study), study)
    envelope_networks = (frame["figures"].astype(str).str.startswith(figures.ENVELOPE_TAG).sum()
                         if not frame.empty else 0)
    best = winner(study)
    retrained = best is not None and is_retrained(best)
    scored = scored_trials(study)
    # the three best candidates of the winner's kind (retrained or estimated), and the baselines alike
    ranked = sorted([t for t in scored if not trial_record(t).baseline and is_retrained(t) == retrained],
                    key=lambda t: t.values[0])[:3]
    baselines = [t for name in study_baselines(view) if (t := baseline_trial(study, name, retrained=retrained))]
    ctx: dict = {"study": study.study_name, "config": cfg,
                 "states": frame["state"].value_counts().to_dict() if not frame.empty else {},
                 "versions": _versions(), "generated": time.strftime("%Y-%m-%d %H:%M:%S"), "figures": {},
                 "notes": _notes(stored, devs, scored), "evaluator": cfg.get("evaluator", "proxy"),
                 "finalist_steps": cfg.get("finalist_steps"), "plan": stored.plan,
                 "envelope_networks": int(envelope_networks)}
    ctx.update(_finalists(view, ctx["finalist_steps"]))
    ctx["wall_time"] = wall_time(view)
    # how each profile's costs were obtained, in the words of `explorer devices` (measured, published,
    # estimate), and its fit errors in one unit
    ctx["devices"] = [{"name": d.name, "description": d.description, "latency": d.latency_basis,
                       "energy": d.energy_basis, "fit": [fit_words(f) for f in fit_errors(d)],
                       "sources": d.provenance.get("sources", []),
                       "conditions": d.provenance.get("conditions")} for d in devs]
    ctx["budgets"] = [d.spec for d in dists]
    ctx["multi_objective"] = len(study.directions) > 1
    if best is not None:
        ctx["best"] = _best(view, best, retrained, devs)
    # a baseline without a row is named, with why (not run, queued, failed, interrupted)
    ctx["missing_baselines"] = missing_baselines(view)
    ctx["no_ratio"] = next((m["why"] for m in ctx["missing_baselines"] if m["name"] == "paper"), "")
    unbeaten = unbeaten_baseline(study)
    ctx["unbeaten"] = ({"label": baseline_label(trial_record(unbeaten).baseline), "value": unbeaten.values[0]}
                       if unbeaten is not None and best is not None else None)
    ctx["table2"] = _table2(ranked + baselines, best, devs, dists, config.metric)
    ctx["references"] = _frame_html(reference_table(devs), "references")
    _add_figures(ctx, view, frame, best, baselines, primary, dists, data)
    ctx["envelope_hint"] = envelope_hint(view, storage_url)
    if best is not None and not frame.empty:
        frame.loc[frame["number"] == best.number, "figures"] = "measured: the winner" if retrained else "estimate: the best"
    ctx["trials"] = (_frame_html(frame[[c for c in TRIAL_COLUMNS if c in frame.columns]], "trials")
                     if not frame.empty else "")
    return ctx


def _tag_envelope(frame: pd.DataFrame, study: optuna.Study) -> pd.DataFrame:
    """``frame`` with the networks ``explorer envelope`` retrained tagged as such in its ``figures``
    column (not as finalists: each is trained for one path alone and can never be the winner), which
    the figures draw apart (explorer.report.figures)."""
    for t in envelope_trials(study):
        tag = f"{figures.ENVELOPE_TAG} for path {dedicated_path(trial_record(t))} (measured)"
        frame.loc[frame["number"] == t.number, "figures"] = tag
    return frame


def _notes(stored: StudyRecord, devs: list[DeviceProfile], scored: list) -> list[str]:
    """What the reader should know about cells left empty and baselines without estimates."""
    notes = []
    lacking = [d.name for d in devs if "int8" not in d.precisions]
    if lacking and any(trial_precision(t) == "int8" for t in scored):
        notes.append(f"int8 designs are not priced on {', '.join(lacking)}: those profiles have no int8 "
                     "rates, so their cells there are empty.")
    for name, why in stored.baselines_not_estimated.items():
        notes.append(f"Baseline {baseline_label(name)} has no search estimate: {why}.")
    return notes


def _finalists(view: StudyView, finalist_steps) -> dict:
    """The finalists' table (estimate beside retrained result), the finalists' agreement (Kendall's tau
    between the two where three or more have both), the measured fidelity of the study's estimate,
    and the retraining steps they really ran."""
    study = view.study
    out = {"finalist_steps": finalist_steps, "finalists": "", "finalists_tau": None, "finalists_rows": 0,
           "fidelity": estimate_fidelity(view)}
    finals = finalist_trials(study)
    recipes = sorted({trial_record(t).finalist.recipe["steps"] for t in finals})
    if recipes:   # a --time-limit plan may have sized them after the study was created
        out["finalist_steps"] = ", ".join(map(str, recipes))
    measured = [trial_record(t) for t in finals if trial_record(t).measured]
    if measured:
        recipe, where = measured[-1].finalist.recipe, measured[-1].measured
        size = "x".join(map(str, where.input_size))
        tune = f", then {recipe['tune_steps']} at {size}" if recipe.get("tune_steps") else ""
        out["measured_recipe"] = (f"finalists and baselines retrained alone {out['finalist_steps']} steps at "
                                  f"{'x'.join(map(str, recipe['input_size']))}{tune}; every path measured at {size} "
                                  f"on the first {where.frames} validation frames of {where.data}")
    fin = finalists_frame(study)
    if not fin.empty:
        agreement = finalists_agreement(study)
        if agreement:
            out["finalists_tau"], out["finalists_rows"] = agreement["tau"], agreement["rows"]
        out["finalists"] = _frame_html(fin, "finalists-table")
    return out


def _best(view: StudyView, best: optuna.trial.FrozenTrial, retrained: bool, devs: list) -> dict:
    """The winner (Table 1 style): its architecture, how its loss was found, its paths on every
    device, and its loss over the paper design's where that has one of the same kind."""
    cand = Candidate.from_dict(trial_record(best).shipped_candidate)
    evaluator = trial_record(best).evaluator_name
    how = "retrained" if retrained else f"estimated by the {evaluator} evaluator"
    out = {"number": best.number, "value": best.values[0], "key": cand.key, "how": how,
           "figures": figures_source(best, view.config.train_size),
           "architecture": cand.describe(), "yaml": cand.to_yaml(),
           "dropped": [DroppedExit.from_dict(d).describe(trial_record(best).error_metric)
                       for d in (trial_record(best).shipped.dropped if trial_record(best).shipped else [])],
           "table": _frame_html(path_table(best, devs), "best-table")}
    paper = baseline_trial(view.study, "paper", retrained=retrained)
    if paper is not None:
        out["ratio"] = best.values[0] / paper.values[0]
    return out


def _table2(trials: list, best, devs: list[DeviceProfile], dists: list, metric: str) -> str:
    """Table 2: a row for each of ``trials``, a column for each device and budget."""
    rows = []
    for t in trials:
        row = {"model": _label(t, best), "trial": t.number}
        for d in devs:
            for dist in dists:
                if dist.kind == "energy" and d.active_power_w <= 0:
                    continue  # no energy model for this device
                row[f"{d.name} {_budget_label(dist)}"] = trial_anytime_loss(t, d, dist, metric)
        rows.append(row)
    return _frame_html(pd.DataFrame(rows), "table2") if rows else ""


def _add_figures(ctx: dict, view: StudyView, frame: pd.DataFrame, best, baselines: list,
                 primary: DeviceProfile, dists: list, data: str | None) -> None:
    """Draws the figures into ``ctx["figures"]``; a figure that cannot be drawn is left out, with a
    note where the reader can do something about it."""
    config = view.config
    found = envelope(view) if best is not None and primary.name == config.device else None
    if found is not None:
        ctx["envelope"] = {"loss": found.loss, "ratio": found.ratio, "networks": len(found.networks),
                           "below_one": found.below_one}
    curve_rows = []
    if best is not None:
        curve_rows.append((_label(best, best), best, figures.COLOURS["best"]))
    curve_rows += [(_label(t, best), t, figures.colour(trial_record(t).baseline)) for t in baselines]
    time_budget = next((d.spec for d in dists if d.kind == "time"), DEFAULT_BUDGET)
    if curve_rows:
        ctx["figures"]["curve_time"] = figures.step_curves(
            curve_rows, primary, time_budget,
            found if found is not None and time_budget == config.budgets[0] else None)
        energy = next((d.spec for d in dists if d.kind == "energy"), None)
        if energy and primary.active_power_w > 0:
            ctx["figures"]["curve_energy"] = figures.step_curves(curve_rows, primary, energy)
    ctx["alt"] = {}
    if not frame.empty and (frame["state"] == "COMPLETE").any() and not ctx["multi_objective"]:
        for name, xcol, xlabel in (("pareto_params", "params", "parameters (last path)"),
                                   ("pareto_macs", "macs", "MACs (last path)"), ("history", None, None)):
            drawn = figures.history(frame) if xcol is None else figures.pareto(frame, xcol, xlabel)
            ctx["figures"][name], ctx["alt"][name] = drawn
    if not ctx["multi_objective"]:
        from optuna.visualization import matplotlib as ovm
        png = figures.optuna_plot(ovm.plot_param_importances, view.study)
        if png:
            ctx["figures"]["importances"] = png
    if best is not None:
        _winner_figures(ctx, view, best, primary, time_budget, data)


def _winner_figures(ctx: dict, view: StudyView, best, primary: DeviceProfile, budget: str,
                    data: str | None) -> None:
    """The winner's paths on a time axis and its depth maps, each with its alt text and caption: the
    times are the cost model's estimates on ``primary``, the errors the winner's own figures."""
    kind = figures_kind(best)
    size = "x".join(map(str, figures.depth_map_size(view, best)))
    errors = (f"measured on the retrained network at {size}" if kind == "measured"
              else f"estimated by the search at {size}")
    timeline, worse = figures.path_timeline(best, primary, budget)
    if timeline:
        ctx["figures"]["paths"] = timeline
        ctx["paths_figure"] = _timeline_words(best, primary, budget, worse, kind, errors)
    png, note = figures.depth_maps(view, best, data, primary)
    if png:
        ctx["figures"]["depth_maps"] = png
        ctx["depth_maps_figure"] = {
            "alt": f"Depth maps of every path of trial {best.number} on the first validation frames at {size}, "
                   "beside each image and its ground truth, coloured by depth in metres",
            "caption": f"The first validation frames at {size}, "
                       + ("the deployment size the winner was measured at and runs at as shipped. " if kind == "measured"
                          else "the study's training size, where the search estimated the winner. ")
                       + f"Each path's column gives its time on {primary.name} (estimated by the cost model) and its "
                         f"RMSE over all the frames its figures come from ({errors}). One colour scale, in metres."}
    elif note:
        ctx["notes"].append(f"Depth maps left out: {note}.")


def _timeline_words(best, device: DeviceProfile, budget: str, worse: dict, kind: str, errors: str) -> dict:
    """The alt text and caption of the winner's paths on a time axis."""
    dist = parse_budget(budget)
    mark = (f"B_max = {dist.upper:g} ms of {dist.spec}: a path ready after it is never returned under that budget"
            if dist.name == "uniform" else f"where {dist.spec} has almost all its mass ({dist.upper:g} ms)")
    badly = "; ".join(f"path {i} is worse than path {j}" for i, j in worse.items())
    order = (f"In red, hatched: {badly}; the runtime never returns such a path (it keeps the better map it "
             "already has), so its time is spent for nothing." if worse else
             "Every path is better than the ones before it.")
    alt = (f"Trial {best.number}'s paths on a time axis: a bar per path up to when its output is ready on "
           f"{device.name} (estimated), its RMSE ({kind}) on the right, the budget's end at {dist.upper:g} ms "
           "marked" + (f"; {badly}" if worse else ""))
    caption = (f"Each bar runs from a frame's arrival to when that path's output is ready on {device.name}, as the "
               f"cost model estimates it (the table's {device.name} ms); on the right, each path's RMSE ({errors}). "
               f"The dashed line is {mark}. {order}")
    return {"alt": alt, "caption": caption}


def write_report(view: StudyView, out_dir: str | Path, devices: Sequence[str] | None = None,
                 budgets: Sequence[str] | None = None, data: str | None = None,
                 curve: Path | None = None, storage_url: str | None = None) -> Path:
    """Writes the report of the study ``view`` reads to ``out_dir/report.html`` (atomically) and returns
    its path. ``curve``: a measured anytime curve (``explorer curve``) to show next to its prediction;
    ``storage_url``: where the study is, for the commands the report suggests."""
    ctx = build_context(view, devices, budgets, data, storage_url)
    curve = curve or Path(out_dir) / "export" / "anytime_curve.json"
    if curve.is_file():
        png = figures.measured_curve(curve)
        if png:
            ctx["figures"]["measured_curve"] = png
    env = Environment(loader=FileSystemLoader(Path(__file__).parent), autoescape=select_autoescape(["html", "j2"]))
    html = env.get_template("report.html.j2").render(**ctx)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    write_atomically(path, html)   # a full disk leaves the report before, and no scratch
    return path
