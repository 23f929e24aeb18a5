"""The anytime curve of an exported model measured on this machine beside the one the cost model
predicts for it (``explorer curve``): how far the prediction can be trusted here. What needs no torch
(the export's own frames, the manifest's prediction, the measurement) is ``explorer.deploy.curve``;
this adds frames read from a data set and a prediction priced with a profile, or calibrated here."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

from explorer.calibration.calibrate import calibrate
from explorer.cost import candidate_cost, get_device
from explorer.cost.devices import DeviceProfile
from explorer.data import open_dataset, require_scores
from explorer.deploy.curve import Prediction, manifest_prediction, measure_curve, read_curve_frames
from explorer.deploy.manifest import Manifest
from explorer.deploy.runtime import AnytimeRunner
from explorer.space import Candidate


def curve_check(model_dir: Path, data: str | None, device: str | None = None, frames: int = 16,
                deadlines: int = 40, progress: Callable[[int, int], None] | None = None,
                provider: str = "CPUExecutionProvider", calibration: dict | None = None,
                calibration_progress: Callable[[str, int, int | None], None] | None = None,
                keep: Callable[[DeviceProfile], None] | None = None,
                say: Callable[[str], None] | None = None) -> dict:
    """The anytime curve measured on this machine next to the one a host profile predicts.

    Per-path losses come from the exported graphs on ``frames`` validation frames of ``data`` (None:
    the frames the export carries, else ``synthetic``); the prediction is the manifest's for
    ``device`` where it holds one, else ``device``'s profile prices the paths (a profile from
    ``explorer calibrate``; calibrated now, with ``provider``, if None, with ``calibration``'s options
    to :func:`calibrate`, and handed to ``keep`` before any deadline runs); the graphs run on
    ``provider``; see :func:`explorer.deploy.curve.measure_curve` for the rest. Written to
    ``model_dir/anytime_curve.json``.
    """
    runner = AnytimeRunner(model_dir, provider=provider)
    manifest = runner.manifest
    if data is None and manifest.curve_frames is not None:
        items, data = read_curve_frames(model_dir, manifest, frames, say), manifest.curve_frames.data
    else:
        data = data or "synthetic"
        ds = open_dataset(data, "val", runner.input_size, train_augment=False)
        items = [ds[i] for i in range(min(frames, len(ds)))]
        require_scores(items, data, "rmse")   # the curve is the RMSE of what each deadline returns
    prediction = manifest_prediction(manifest, device) if device else None
    if prediction is None:
        if device:
            profile = get_device(device)
        else:
            profile = calibrate(**{"scale": 0.5, **(calibration or {})}, provider=provider,
                                progress=calibration_progress)
            if keep:
                keep(profile)
        prediction = _priced(manifest, profile, runner.input_size)
    return measure_curve(runner, items, data, prediction, deadlines, progress)


def _priced(manifest: Manifest, profile: DeviceProfile, input_size: tuple[int, int]) -> Prediction:
    """The paths priced with ``profile``: at the model's precision where it prices it, else fp32."""
    cand = Candidate.from_dict(manifest.candidate)
    priced = manifest.precision if manifest.precision in profile.precisions else "fp32"
    costs = candidate_cost(dataclasses.replace(cand, precision=priced), input_size).path_latency_ms(profile)
    return Prediction(device=profile.name, latency_ms=list(costs), precision=priced)
