"""The part of ``explorer curve`` that needs no torch, so that the runtime install has it too: the
validation frames an export carries (``curve_frames.npz``), the prediction its manifest holds for a
device, and the anytime curve measured on this machine beside a prediction.

The full package's ``explorer.calibration.curve`` adds what needs torch: frames read from a data set,
and a prediction priced with a profile the manifest does not hold (or calibrated here)."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from explorer.anytime import anytime_loss
from explorer.deploy.manifest import (CURVE_FRAMES, MANIFEST, CurveFrames, Manifest, curve_frames_file, file_sha256,
                                      read_manifest)
from explorer.deploy.runtime import AnytimeRunner, measured_anytime, path_metrics
from explorer.errors import UserError
from explorer.files import read_yaml, write_json

#: how many validation frames an export carries for ``explorer curve`` (its default ``--frames``)
CURVE_FRAME_COUNT = 16
#: what each stored frame holds, as a data set item holds it; ``scan_rows`` too where the graphs take them
FRAME_KEYS = ("image", "scan", "depth")
ROWS = "scan_rows"
CURVE_FILE = "anytime_curve.json"


@dataclass(frozen=True)
class Prediction:
    """Each path's predicted latency (cumulative, path 0 first) on ``device``, priced at ``precision``,
    from ``source``: the export's manifest, or a profile priced here."""

    device: str
    latency_ms: list[float]
    precision: str
    source: str = "profile"


def write_curve_frames(folder: Path, items: Sequence[dict], data: str, rows_input: bool) -> CurveFrames | None:
    """Writes the first :data:`CURVE_FRAME_COUNT` of ``items`` (validation frames of ``data`` at the
    export's input size) to ``folder``/:data:`CURVE_FRAMES`, each array in the dtype the data set gives
    it, and returns the manifest's entry for them; None, and no file, where they hold no depth (a curve
    is the RMSE of what each deadline returns)."""
    items = list(items[:CURVE_FRAME_COUNT])
    if not any(bool((np.asarray(f["depth"]) > 0).any()) for f in items):
        return None
    keys = FRAME_KEYS + ((ROWS,) if rows_input else ())
    path = Path(folder) / CURVE_FRAMES
    with open(path, "wb") as f:
        np.savez_compressed(f, **{k: np.stack([np.asarray(item[k]) for item in items]) for k in keys})
    return CurveFrames(file=CURVE_FRAMES, data=data, split="val", frames=len(items), sha256=file_sha256(path))


def read_curve_frames(model_dir: Path, manifest: Manifest, frames: int,
                      say: Callable[[str], None] | None = None) -> list[dict]:
    """The first ``frames`` of the curve frames the export in ``model_dir`` carries (all of them, said
    through ``say``, where it carries fewer), checked against the manifest's hash."""
    path = curve_frames_file(model_dir, manifest)
    try:
        with np.load(path, allow_pickle=False) as stored:
            arrays = {k: stored[k] for k in stored.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path}: cannot read the curve frames ({exc}): export the model again") from None
    keys = FRAME_KEYS + ((ROWS,) if manifest.scan_rows_input else ())
    count = manifest.curve_frames.frames
    if any(k not in arrays or len(arrays[k]) != count for k in keys):
        raise UserError(f"{path}: does not hold the {count} frames ({', '.join(keys)}) the manifest names: export "
                        "the model again")
    if frames > count and say:
        say(f"--frames {frames}: the export carries {count} validation frames of {manifest.curve_frames.data}; "
            f"measuring on those {count}")
    return [{k: arrays[k][i] for k in keys} for i in range(min(frames, count))]


def manifest_prediction(manifest: Manifest, device: str) -> Prediction | None:
    """The prediction the manifest's ``expected_cost`` holds for ``device`` (a device name, or a profile
    YAML file whose ``name`` it holds); None where it holds none for it."""
    name = device
    if name not in manifest.expected_cost and device.endswith((".yaml", ".yml")) and Path(device).is_file():
        profile = read_yaml(Path(device), "device profile (YAML)")
        name = str(profile.get("name", "")) if isinstance(profile, dict) else ""
    cost = manifest.expected_cost.get(name)
    if cost is None or not cost.latency_ms:
        return None
    precision = manifest.expected_cost_precision or str(manifest.candidate.get("precision", "fp32"))
    return Prediction(device=name, latency_ms=list(cost.latency_ms), precision=precision, source="manifest")


def unpriced_device(manifest: Manifest, device: str | None) -> str:
    """Why the runtime install cannot predict ``device``'s curve for this export, and how to add it."""
    names = ", ".join(sorted(manifest.expected_cost)) or "no device"
    given = f"--device {device} is not among them" if device else "no --device was given"
    return (f"in the runtime install explorer curve predicts with the costs the export's manifest holds, and {given}: "
            f"this export prices {names} (--device NAME); to price this device, calibrate it with a probe bundle "
            "(on the host `explorer calibrate --bundle probe.tar`, here `tar xf probe.tar && python3 probe.pyz --out "
            "results.json`, on the host `explorer calibrate --fit results.json --out mybox.yaml`) and export again "
            "with `explorer export ... --device mybox.yaml`")


def device_curve(model_dir: Path, device: str | None, frames: int = CURVE_FRAME_COUNT, deadlines: int = 40,
                 progress: Callable[[int, int], None] | None = None, provider: str = "CPUExecutionProvider",
                 say: Callable[[str], None] | None = None) -> dict:
    """``explorer curve`` without torch: the frames the export carries, run on this machine, beside the
    prediction the manifest holds for ``device``."""
    manifest = read_manifest(model_dir)
    prediction = manifest_prediction(manifest, device) if device else None
    if prediction is None:
        raise UserError(unpriced_device(manifest, device))
    if manifest.curve_frames is None:
        raise UserError(f"{Path(model_dir) / MANIFEST}: the export carries no curve frames (its frames had no "
                        "depth, or an older version exported it): export it again with anytime-explorer on data "
                        "with depth (--data), or run explorer curve --data DATA in anytime-explorer")
    items = read_curve_frames(model_dir, manifest, frames, say)
    runner = AnytimeRunner(model_dir, provider=provider)
    return measure_curve(runner, items, manifest.curve_frames.data, prediction, deadlines, progress)


def measure_curve(runner: AnytimeRunner, items: list[dict], data: str, prediction: Prediction, deadlines: int,
                  progress: Callable[[int, int], None] | None = None) -> dict:
    """Runs ``items`` under ``deadlines`` deadlines spread evenly over (0, B_max), B_max = 1.25 x the
    predicted last path, and writes the measured curve beside the predicted one to the model folder's
    ``anytime_curve.json``."""
    from explorer.space import Candidate
    manifest = runner.manifest
    losses = [m["rmse"] for m in path_metrics(runner, items)]
    costs = prediction.latency_ms
    b_max = 1.25 * costs[-1]
    grid = (np.arange(deadlines) + 0.5) * b_max / deadlines
    measured: dict[str, list] = {"deadlines_ms": [], "loss": [], "mean_path": []}
    for i, d in enumerate(grid):
        part = measured_anytime(runner, items, np.array([d]))
        for k in measured:
            measured[k] += part[k]
        if progress:
            progress(i + 1, len(grid))
    result = {"candidate_key": manifest.candidate_key or Candidate.from_dict(manifest.candidate).key,
              "device": prediction.device, "predicted_from": prediction.source, "provider": runner.provider,
              "precision": manifest.precision, "priced_precision": prediction.precision, "frames": len(items),
              "data": data, "input_size": list(runner.input_size), "b_max_ms": b_max,
              "path_losses": losses, "predicted_costs_ms": costs,
              "predicted_anytime_loss": anytime_loss(costs, losses, f"time:uniform:{b_max}ms"),
              "measured": measured, "measured_anytime_loss": float(np.mean(measured["loss"]))}
    write_json(runner.dir / CURVE_FILE, result)
    return result
