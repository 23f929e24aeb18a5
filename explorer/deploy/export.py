"""``explorer export``: a trained candidate as ONNX graphs in execution order, cut so that every
exit's depth map is available as soon as its stage ends (one graph per group of stages ending with
an exit, path 0 on its own), plus a manifest. Verified against PyTorch at export time."""

from __future__ import annotations

import dataclasses
import math

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from explorer import __version__
from explorer.cost import candidate_cost, get_device
from explorer.deploy.curve import CURVE_FRAME_COUNT, write_curve_frames
from explorer.deploy.manifest import (MANIFEST, CurveFrames, ExpectedCost, Manifest, Measured, PathMetrics, Source,
                                      Stage, Verification, file_sha256, write_manifest)
from explorer.deploy.quantize import MAX_DEGRADATION
from explorer.deploy.sessions import session
from explorer.errors import UserError
from explorer.files import replacing_folder, scratch_dir
from explorer.model import AnytimeDepthNet
from explorer.model.onnx import OPSET, SCAN_ROWS, example_inputs, export_segments
from explorer.training.train import network_from_checkpoint, trained_on

TOLERANCE = 1e-4


def verify(graphs, net: AnytimeDepthNet, input_size: tuple[int, int], scan_row: int,
           rows_input: bool = False) -> float:
    """Max |onnxruntime - torch| over every path's depth map on a random input."""
    env = example_inputs(input_size, rows_input=rows_input)
    with torch.no_grad():
        ref = [d.numpy() for d in net.eval()(env["image"], env["scan"], env.get(SCAN_ROWS, scan_row))]
    feeds = {k: v.numpy() for k, v in env.items()}
    outs: dict[str, np.ndarray] = {}
    for _, model in graphs:
        sess = session(model)   # the process's shared pool: its first session sizes it
        res = sess.run(None, {i.name: (outs | feeds)[i.name] for i in sess.get_inputs()})
        outs.update({o.name: v for o, v in zip(sess.get_outputs(), res)})
    return max(float(np.abs(outs[f"depth_{p}"] - r).max()) for p, r in enumerate(ref))


@dataclass(frozen=True)
class Quantization:
    """What ``explorer export --quantize int8`` asks for (see :mod:`explorer.deploy.quantize`)."""

    data: str | None = "synthetic"   # None: the frames the export is measured on (a study's or checkpoint's own)
    calibration_frames: int = 32
    eval_frames: int = 64
    max_degradation: float = MAX_DEGRADATION
    force: bool = False
    # which stage graphs are int8: "faster" (measured here), "all", or those named (as searched)
    stages: "str | tuple[str, ...]" = "faster"


@dataclass(frozen=True)
class Measurement:
    """The frames an export's paths are measured on with onnxruntime: the first ``frames`` of the
    validation split of ``data`` (a study's own: the frames its figures are measured on; None, for a
    checkpoint: the data it was trained on)."""

    data: str | None = "synthetic"
    frames: int = 96


def measure_export(model_dir: Path, measurement: Measurement, input_size: tuple[int, int]
                   ) -> tuple[PathMetrics, Measured]:
    """Per-path metrics of the graphs in ``model_dir`` as they stand, run by the project's runtime on
    ``measurement``'s frames at ``input_size``, and what they were measured on."""
    from explorer.data import open_dataset
    from explorer.deploy.runtime import AnytimeRunner, path_metrics
    ds = open_dataset(measurement.data, "val", tuple(input_size), train_augment=False)
    frames = [ds[i] for i in range(min(measurement.frames, len(ds)))]
    if not frames:
        raise UserError(f"--data {measurement.data}: its validation split has no frames to measure the export on")
    metrics = path_metrics(AnytimeRunner(model_dir, warmup=False, arenas="shared"), frames)
    # a metric the frames cannot give (RMSE without depth, the photometric error without motion) is left out
    return ([{k: v for k, v in m.items() if k != "path" and not math.isnan(v)} for m in metrics],
            Measured(data=measurement.data, split="val", frames=len(frames), input_size=tuple(input_size),
                     by="onnxruntime, the exported graphs"))


def export_network(net: AnytimeDepthNet, out_dir: Path, input_size: tuple[int, int],
                   scan_row: int | None = None, path_metrics: list[dict] | None = None,
                   devices: Sequence[str] = ("tx2", "rpi4"), source: dict | None = None,
                   quantization: Quantization | None = None,
                   progress: Callable[[str], None] | None = None,
                   measurement: Measurement | None = None, tuned_size: tuple[int, int] | None = None) -> Manifest:
    """Writes the stage graphs and the manifest to ``out_dir``, whole: everything is built, checked
    (and, with ``quantization``, quantized and measured) in a scratch folder that then replaces
    ``out_dir``; a refused or killed export leaves ``out_dir`` as it was. The manifest records each
    graph's SHA-256, which the runtime checks. With ``measurement`` every path of the exported graphs
    is measured on its frames at ``input_size`` and the manifest's ``path_metrics`` are those figures,
    never ``path_metrics`` given for another size; ``tuned_size`` is the size the weights were trained
    (or tuned) at, recorded beside it."""
    rows_input = measurement is not None and slanted_scans(measurement.data, input_size)
    if rows_input and quantization is not None:
        raise UserError(f"int8 export of a network whose scans lie on slanted lines ({measurement.data}) is not "
                        "supported yet; export it in fp32 (without --quantize)")
    with replacing_folder(out_dir, MANIFEST) as scratch:
        manifest = _export_fp32(net, scratch, input_size, scan_row, path_metrics, devices, source, rows_input)
        if tuned_size is not None:
            manifest.tuned_size = tuple(tuned_size)
        if measurement is not None:
            write_manifest(scratch, manifest)   # what the runtime reads
            if progress:
                progress(f"measuring every path on {measurement.frames} validation frames of {measurement.data}")
            manifest.path_metrics, manifest.measured = measure_export(scratch, measurement, input_size)
        write_manifest(scratch, manifest)   # what quantization reads and rewrites
        if quantization is not None:
            from explorer.deploy.quantize import (
                quantize_export,  # onnxruntime.quantization: only when asked
            )
            q = quantization
            manifest = quantize_export(scratch, q.data, q.calibration_frames, q.eval_frames, q.max_degradation,
                                       q.force, progress, q.stages)
            manifest.path_metrics_trained = manifest.path_metrics
            manifest.path_metrics = manifest.path_metrics_int8
            if manifest.expected_cost_precision != "int8":   # the profiles priced the fp32 network
                manifest.expected_cost_note = (
                    "fp32 estimates: the device profiles price this network's layers as fp32, not the int8 graphs "
                    "exported (`explorer curve` measures these on a machine)")
        if measurement is not None:   # what `explorer curve` measures on where it cannot read the data
            manifest.curve_frames = store_curve_frames(scratch, measurement.data, input_size, rows_input)
        for stage in manifest.stages:
            stage.sha256 = file_sha256(scratch / stage.file)
        write_manifest(scratch, manifest)
    return manifest


def store_curve_frames(folder: Path, data: str, input_size: tuple[int, int], rows_input: bool) -> CurveFrames | None:
    """Writes the first validation frames of ``data`` at ``input_size`` into the export in ``folder``
    for ``explorer curve`` (:func:`explorer.deploy.curve.write_curve_frames`); None where they have no
    depth."""
    from explorer.data import open_dataset
    ds = open_dataset(data, "val", tuple(input_size), train_augment=False)
    items = [ds[i] for i in range(min(CURVE_FRAME_COUNT, len(ds)))]
    return write_curve_frames(folder, items, data, rows_input)


def slanted_scans(data: str, input_size: tuple[int, int], frames: int = 8) -> bool:
    """Whether the scans of ``data``'s first validation frames leave one row (a tilted, rolled or offset
    LiDAR): the network then takes each column's row, and so do its graphs."""
    from explorer.data import open_dataset
    ds = open_dataset(data, "val", tuple(input_size), train_augment=False)
    for i in range(min(frames, len(ds))):
        rows = ds[i]["scan_rows"]
        if bool((rows != rows[0]).any()):
            return True
    return False


def _export_fp32(net: AnytimeDepthNet, out_dir: Path, input_size: tuple[int, int], scan_row: int | None,
                 path_metrics: list[dict] | None, devices: Sequence[str], source: dict | None,
                 rows_input: bool = False) -> Manifest:
    h, w = input_size
    if h % net.stride or w % net.stride:
        raise UserError(f"input {h}x{w} does not divide by the encoder stride {net.stride}")
    scan_row = h // 2 if scan_row is None else scan_row
    net = net.eval()
    graphs = export_segments(net, input_size, scan_row, rows_input)
    diff = verify(graphs, net, input_size, scan_row, rows_input)
    if diff > TOLERANCE:
        raise RuntimeError(f"ONNX export differs from PyTorch by {diff:.2e} (> {TOLERANCE:g}): not written")
    stages = []
    for i, (seg, model) in enumerate(graphs):
        file = f"{i:02d}_path{seg['path']}.onnx"
        (out_dir / file).write_bytes(model)
        stages.append(Stage(file=file, **seg))
    cost = candidate_cost(net.candidate, input_size)
    expected = {}
    for d in devices:
        prof = get_device(d)
        if cost.precision not in prof.precisions:
            continue      # this profile cannot price the candidate's precision
        expected[prof.name] = ExpectedCost(latency_ms=cost.path_latency_ms(prof), energy_j=cost.path_energy_j(prof),
                                           calibrated=prof.calibrated)
    return Manifest(
        format="anytime-explorer/1", explorer_version=__version__, opset=OPSET,
        candidate=net.candidate.to_dict(), candidate_key=net.candidate.key,
        architecture=net.candidate.describe(), input_size=(h, w), scan_row=scan_row,
        image="RGB in [0, 1], (1, 3, H, W) float32", scan="(1, W) float32 metres, 0 = no return",
        scan_rows_input=rows_input,
        stages=stages, paths=net.candidate.num_paths,
        path_metrics=path_metrics or [], expected_cost=expected, expected_cost_precision=cost.precision,
        params=[p for p, _ in cost.path_params_macs()], macs=[m for _, m in cost.path_params_macs()],
        verification=Verification(max_abs_diff=diff, tolerance=TOLERANCE), source=Source(**(source or {})),
        precision="fp32",
    )


def export_from_checkpoint(ckpt: Path, out_dir: Path, input_size: tuple[int, int] | None = None,
                           devices: Sequence[str] | None = None, quantization: Quantization | None = None,
                           progress: Callable[[str], None] | None = None,
                           measurement: Measurement | None = None) -> Manifest:
    net, state = network_from_checkpoint(ckpt)
    trained = tuple(state["train_config"]["input_size"])
    # the frames it was trained for, unless told
    if (measurement is not None and measurement.data is None) or (quantization is not None and
                                                                  quantization.data is None):
        data = trained_on(state, ckpt)
        if measurement is not None and measurement.data is None:
            measurement = dataclasses.replace(measurement, data=data)
        if quantization is not None and quantization.data is None:
            quantization = dataclasses.replace(quantization, data=data)
    size = tuple(input_size or trained)
    return export_network(net, out_dir, size, devices=devices or ("tx2", "rpi4"),
                          source={"checkpoint": str(ckpt)}, quantization=quantization, progress=progress,
                          measurement=measurement, tuned_size=trained)


def quantization_effect(net, input_size: tuple[int, int], data: str, calibration_frames: int = 16,
                        eval_frames: int = 32, stages: "str | tuple[str, ...]" = "faster") -> dict:
    """How quantizing ``net``'s stage graphs to int8 (``stages``, as ``quantize_export`` reads it)
    changes each path's metrics, measured with onnxruntime on ``eval_frames`` validation frames of
    ``data`` (fp32 and int8 graphs alike): per path, each metric's int8 / fp32 ratio. What a search
    applies to an int8 candidate's estimate, so that it is compared with fp32 ones on the same frames."""
    import math
    if stages == ():   # no graph int8 (none pays on the device): its fp32 metrics
        paths = net.candidate.num_paths
        return {"ratios": [{}] * paths, "rmse_degradation": [0.0] * paths, "frames": 0, "int8_graphs": []}
    with scratch_dir("int8") as tmp:
        m = export_network(net, Path(tmp) / "model", input_size, devices=(),
                           quantization=Quantization(data=data, calibration_frames=calibration_frames,
                                                     eval_frames=eval_frames, max_degradation=math.inf, force=True,
                                                     stages=stages))
    before, after = m.path_metrics_fp32, m.path_metrics_int8
    ratios = [{k: (a[k] / b[k] if b[k] else 1.0) for k in b if isinstance(b[k], (int, float))}
              for a, b in zip(after, before)]
    return {"ratios": ratios, "rmse_degradation": m.quantization.rmse_degradation,
            "frames": m.quantization.evaluation.frames,
            "int8_graphs": [s.name for s in m.stages if s.precision == "int8"]}


