"""Exporting a study's trial (its winner by default) as ONNX stage graphs, with what the study knows
of it: its data, its device, whether it was searched as int8."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable, Sequence

from explorer.deploy.export import Manifest, Measurement, Quantization, export_network
from explorer.errors import UserError
from explorer.model.shipped import ship, shipped_network
from explorer.study.records import trial_record
from explorer.study.results import best_trial, scored_trials, trial_network, winner
from explorer.study.storage import load_study
from explorer.study.view import study_view

#: ``export_from_study(quantization=AS_SEARCHED)``: int8 if the trial's candidate was searched as int8
AS_SEARCHED = "as-searched"


def export_from_study(study_name: str, trial_number: int | None, out_dir: Path, storage: str | None,
                      reports: Path, input_size: tuple[int, int] | None = None,
                      devices: Sequence[str] | None = None, quantization: Quantization | str | None = None,
                      progress: Callable[[str], None] | None = None, data: str | None = None,
                      eval_frames: int | None = None) -> Manifest:
    """Exports trial ``trial_number`` of study ``study_name`` (default: the winner, else the best
    baseline) to ``out_dir``; ``quantization=AS_SEARCHED``: int8 where the trial was searched as int8.
    Every path of the exported graphs is measured on the first ``eval_frames`` validation frames of
    ``data`` (default: the study's data and the frames its figures come from); the study's own figures
    are kept beside them only when they were measured at the size exported. Its costs are priced on
    ``devices`` (default: the profile the study stored, then the comparison devices)."""
    view = study_view(load_study(study_name, storage, reports))
    study = view.study
    trials = {t.number: t for t in scored_trials(study)}
    if trial_number is None:
        trial = winner(study) or best_trial(study, baseline=True)
        if trial is None:
            raise UserError(f"study '{study_name}' has no completed trial to export")
    elif trial_number not in trials:
        raise UserError(f"trial {trial_number} of '{study_name}' is not a completed trial (completed: "
                        f"{sorted(trials)[:20]})")
    else:
        trial = trials[trial_number]
    net = trial_network(view, trial)
    cfg = view.config
    rec = trial_record(trial)
    measured = rec.measured     # a retrained trial: measured at the deployment size
    measurement = Measurement(data=data or cfg.data,
                              frames=eval_frames or (measured.frames if measured else None) or cfg.val_limit or 96)
    if isinstance(quantization, Quantization) and quantization.data is None:   # the study's frames
        quantization = dataclasses.replace(quantization, data=measurement.data)
    if quantization == AS_SEARCHED:   # an int8 candidate was costed and measured as int8: export it so
        searched = rec.int8_graphs   # the stage graphs its device priced int8
        quantization = Quantization(data=measurement.data, eval_frames=measurement.frames,
                                    stages="faster" if searched is None else tuple(searched)) \
            if net.candidate.precision == "int8" else None
    size = tuple(input_size or cfg.input_size)
    devs = list(devices or view.devices())
    tuned = tuple(measured.input_size) if measured else tuple(cfg.train_size)
    source = {"study": study_name, "trial": trial.number, "objective": trial.values[0],
              "figures": "retrained, measured" if measured else "estimated by the search"}
    if measured and tuple(measured.input_size) == size:
        source.update(study_path_metrics=rec.path_metrics, study_measured=measured.model_dump(mode="json"))
    if rec.shipped is not None:   # the exits left out of what ships, and why
        source.update(trained_candidate=rec.candidate, dropped_exits=rec.shipped.dropped)
    manifest = export_network(net, out_dir, size, devices=devs, source=source, quantization=quantization,
                              progress=progress, measurement=measurement, tuned_size=tuned)
    if quantization is not None or cfg.keep_every_exit:
        return manifest
    # The study decided what ships on its own figures (estimates, or another size): the exported graphs,
    # measured here at the deployment size, decide again, so that no path shipped is less accurate than
    # one returned before it.
    again = _ship_as_measured(net.candidate, manifest, cfg.metric, rec, size)
    if again is None:
        return manifest
    shipped, dropped = again
    if "study_path_metrics" in source:   # the study's figures of the paths that still ship
        source["study_path_metrics"] = [source["study_path_metrics"][p] for p in shipped.paths]
    if progress:
        progress(f"leaving out {', '.join(d['exit'] for d in dropped[len(source.get('dropped_exits') or []):])}: "
                 f"no more accurate than an earlier path as exported; exporting again")
    source.update(trained_candidate=rec.candidate, dropped_exits=dropped)
    return export_network(shipped_network(net, shipped.candidate), out_dir, size, devices=devs, source=source,
                          progress=progress, measurement=measurement, tuned_size=tuned)


def _ship_as_measured(exported, manifest: Manifest, metric: str, rec, size: tuple[int, int]):
    """(the network that ships, every exit left out of the trained network) where the export's own per-path figures
    leave out more exits than the study did; None where they leave out none (or cannot tell: a figure
    missing). Exits dropped here are numbered by the trained network's paths, like the study's."""
    losses = [m.get(metric, math.nan) for m in manifest.path_metrics]
    if len(losses) != exported.num_paths or not all(math.isfinite(v) for v in losses):
        return None
    shipped = ship(exported, losses)
    if not shipped.dropped:
        return None
    trained_paths = rec.shipped.trained_paths if rec.shipped is not None else list(range(exported.num_paths))
    where = f"the exported graphs at {size[0]}x{size[1]}"
    dropped = list(rec.shipped.dropped if rec.shipped is not None else []) + [
        {**d.to_dict(), "path": trained_paths[d.path], "better_path": trained_paths[d.better_path],
         "measured_on": where} for d in shipped.dropped]
    return shipped, dropped
