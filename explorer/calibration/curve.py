"""The anytime curve of an exported model measured on this machine beside the one the cost model
predicts for it (``explorer curve``): how far the prediction can be trusted here."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from explorer.anytime import anytime_loss
from explorer.calibration.calibrate import calibrate
from explorer.cost import candidate_cost, get_device
from explorer.cost.devices import DeviceProfile
from explorer.data import open_dataset, require_scores
from explorer.deploy.runtime import AnytimeRunner, measured_anytime, path_metrics
from explorer.files import write_json
from explorer.space import Candidate


def curve_check(model_dir: Path, data: str, device: str | None = None, frames: int = 16,
                deadlines: int = 40, progress: Callable[[int, int], None] | None = None,
                provider: str = "CPUExecutionProvider", calibration: dict | None = None,
                calibration_progress: Callable[[str, int, int | None], None] | None = None,
                keep: Callable[[DeviceProfile], None] | None = None) -> dict:
    """The anytime curve measured on this machine next to the one a host profile predicts.

    Per-path losses come from the exported graphs on ``frames`` validation frames; the prediction
    prices the paths with ``device`` (a profile from ``explorer calibrate``; calibrated now, with
    ``provider``, if None, with ``calibration``'s options to :func:`calibrate`, and handed to ``keep``
    before any deadline runs); the graphs run on ``provider``;
    the measurement runs every frame under ``deadlines`` deadlines spread evenly over (0, B_max),
    B_max = 1.25 x the predicted last path. Written to ``model_dir/anytime_curve.json``.
    """
    runner = AnytimeRunner(model_dir, provider=provider)
    cand = Candidate.from_dict(runner.manifest.candidate)
    ds = open_dataset(data, "val", runner.input_size, train_augment=False)
    items = [ds[i] for i in range(min(frames, len(ds)))]
    require_scores(items, data, "rmse")   # the curve is the RMSE of what each deadline returns
    losses = [m["rmse"] for m in path_metrics(runner, items)]
    if device:
        profile = get_device(device)
    else:
        profile = calibrate(**{"scale": 0.5, **(calibration or {})}, provider=provider, progress=calibration_progress)
        if keep:
            keep(profile)
    precision = runner.manifest.precision
    priced = precision if precision in profile.precisions else "fp32"   # else the fp32 prediction, said so
    costs = candidate_cost(dataclasses.replace(cand, precision=priced), runner.input_size).path_latency_ms(profile)
    b_max = 1.25 * costs[-1]
    grid = (np.arange(deadlines) + 0.5) * b_max / deadlines
    measured = {"deadlines_ms": [], "loss": [], "mean_path": []}
    for i, d in enumerate(grid):
        part = measured_anytime(runner, items, np.array([d]))
        for k in ("deadlines_ms", "loss", "mean_path"):
            measured[k] += part[k]
        if progress:
            progress(i + 1, len(grid))
    result = {"candidate_key": cand.key, "device": profile.name, "provider": provider,
              "precision": precision, "priced_precision": priced, "frames": len(items), "data": data,
              "input_size": list(runner.input_size), "b_max_ms": b_max,
              "path_losses": losses, "predicted_costs_ms": costs,
              "predicted_anytime_loss": anytime_loss(costs, losses, f"time:uniform:{b_max}ms"),
              "measured": measured, "measured_anytime_loss": float(np.mean(measured["loss"]))}
    write_json(Path(model_dir) / "anytime_curve.json", result)
    return result
