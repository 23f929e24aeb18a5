"""int8 deployment: an exported model's stage graphs quantized statically with onnxruntime
(QDQ format: int8 weights per output channel, uint8 activations whose ranges are calibrated on
frames of a data set), and every path's metrics measured again after quantization.

Each stage graph is calibrated on the inputs it really receives: the float model runs the
calibration frames and every stage's inputs are kept. Only the layers where int8 pays are quantized
(``quantizes``): ungrouped convolutions whose every output sums at least ``MIN_INT8_REDUCTION``
products, transposed convolutions and matrix products. onnxruntime fuses the QDQ pairs around each
into one int8 kernel; depthwise convolutions, thin ones (the RGB stem, the exit heads' last layers),
resizes, additions and concatenations stay float. Path 0 (the scan) has nothing to quantize.

Weights are quantized to 7 bits (``reduce_range``): x86 CPUs without VNNI multiply uint8 by int8 in
pairs summed into int16 (VPMADDUBSW), which saturates with full-range weights; measured on one such
machine (AVX2), full range degraded the paper design's last path by 29% RMSE, 7 bits by under 2%.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from explorer.errors import UserError

QUANTIZED_OPS = ["Conv", "ConvTranspose", "MatMul", "Gemm"]
#: An int8 convolution is quantized only when each output sums at least this many products (its
#: in-channels x kernel area): below it, onnxruntime's int8 kernel with the quantize / dequantize
#: around it took longer than the float layer (the 27-product stem 1.9x, a 16 -> 8 exit head at
#: 224x224 1.45x), from 64 products on 0.57-0.86x (benchmarks/bench_int8_layers.py, this AVX2 machine).
MIN_INT8_REDUCTION = 32
#: Workload kinds an int8 export may quantize: depthwise convolutions never are (onnxruntime's int8
#: depthwise kernels took 1.1-1.7x as long as its float ones, same benchmark).
QUANTIZABLE_KINDS = ("pointwise", "pointwise_1ch", "conv", "conv1d", "deconv")


def quantizes(kind: str, in_channels: int, kernel_area: int) -> bool:
    """Whether an int8 export quantizes a layer of workload ``kind`` (an ungrouped convolution of
    ``in_channels`` x ``kernel_area`` products per output, or a transposed one)."""
    if kind == "deconv":
        return True
    return kind in QUANTIZABLE_KINDS and in_channels * kernel_area >= MIN_INT8_REDUCTION


def workload_quantized(w) -> bool:
    """``quantizes`` for a cost-model ``Workload``. One whose shape is unknown (stored by a study
    before this rule) counts as quantized when its kind may be: every convolution but a depthwise one."""
    if not w.in_shape:
        return w.kind in QUANTIZABLE_KINDS
    return quantizes(w.kind, w.in_shape[0], w.kernel if w.kind == "conv1d" else w.kernel * w.kernel)


def _float_convolutions(model) -> list[str]:
    """Names of the Conv nodes of ``model`` (an onnx ModelProto) that ``quantizes`` leaves float."""
    weights = {i.name: tuple(i.dims) for i in model.graph.initializer}
    keep = []
    for n in model.graph.node:
        if n.op_type != "Conv":
            continue
        group = next((a.i for a in n.attribute if a.name == "group"), 1)
        dims = weights.get(n.input[1]) if len(n.input) > 1 else None   # (out, in / group, *kernel)
        if dims is None or len(dims) < 3 or not quantizes("conv" if group == 1 else "depthwise", dims[1],
                                                          int(np.prod(dims[2:]))):
            keep.append(n.name)
    return keep


#: a path may lose at most this fraction of its RMSE to quantization unless --force
MAX_DEGRADATION = 0.03


def _frames(data: str, input_size: tuple[int, int], count: int, split: str) -> list[dict]:
    from explorer.data import open_dataset
    ds = open_dataset(data, split, input_size, train_augment=False)
    if len(ds) == 0:
        raise UserError(f"--data {data}: its {split} split has no frames to quantize with")
    step = max(len(ds) // count, 1)   # spread over the split, not its first scenes only
    return [ds[i] for i in range(0, len(ds), step)[:count]]


def stage_inputs(model_dir: Path, frames: list[dict]) -> list[list[dict[str, np.ndarray]]]:
    """For each stage graph of an exported model, the inputs it receives on each frame."""
    from explorer.runtime import AnytimeRunner
    runner = AnytimeRunner(model_dir, warmup=False, blocked_handoff=False)   # the graphs' own inputs
    per_stage: list[list[dict[str, np.ndarray]]] = [[] for _ in runner.sessions]
    for f in frames:
        img, scan = runner.check(f["image"].numpy(), f["scan"].numpy())
        env = {"image": img, "scan": scan}
        for k, (_, sess, ins, outs) in enumerate(runner.sessions):
            per_stage[k].append({n: env[n] for n in ins})
            env.update(zip(outs, sess.run(outs, {n: env[n] for n in ins})))
    return per_stage


class _Feeds:
    """onnxruntime.quantization's CalibrationDataReader over recorded stage inputs."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]) -> None:
        self._it = iter(feeds)

    def get_next(self):
        return next(self._it, None)


def quantize_graph(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    """Writes ``src`` quantized to ``dst``; False (and a plain copy) when it has nothing to quantize.
    onnxruntime.quantization makes sessions with thread pools of their own, which a process whose
    sessions share the global pool (``probe_script.session``) may not: there it runs in a child process."""
    from explorer.cost.probe_script import shared_pool_threads
    if shared_pool_threads() is not None:
        return _quantize_in_child(Path(src), Path(dst), feeds)
    return _quantize(Path(src), Path(dst), feeds)


_WORKER: list = []   # one child process, started on first use and kept for the rest of this process


def _quantize_in_child(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    """Sends the job to the worker (``python -m explorer.quantize``: pickles over its stdin and stdout)."""
    import pickle
    import subprocess
    import sys
    if not _WORKER or _WORKER[0].poll() is not None:
        _WORKER[:] = [subprocess.Popen([sys.executable, "-m", "explorer.quantize"], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)]
    worker = _WORKER[0]
    try:
        pickle.dump((str(src), str(dst), feeds), worker.stdin)
        worker.stdin.flush()
        ok, result = pickle.load(worker.stdout)
    except (EOFError, BrokenPipeError, pickle.UnpicklingError):
        worker.kill()
        raise RuntimeError(f"the quantization worker died while quantizing {src.name}") from None
    if not ok:
        raise RuntimeError(f"quantizing {src.name} failed: {result}")
    return result


def _quantize(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process
    model = onnx.load(str(src))
    keep_float = _float_convolutions(model)
    if not any(n.op_type in QUANTIZED_OPS and n.name not in keep_float for n in model.graph.node):
        dst.write_bytes(src.read_bytes())
        return False
    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(src), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(dst), _Feeds(feeds), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        reduce_range=True, op_types_to_quantize=QUANTIZED_OPS,
                        nodes_to_exclude=_float_convolutions(onnx.load(str(prepared))),
                        calibrate_method=CalibrationMethod.MinMax)
    return True


def path_metrics(model_dir: Path, frames: list[dict]) -> list[dict[str, float]]:
    """Per-path metrics of the export in ``model_dir`` as its graphs stand now (fp32 or int8)."""
    from explorer import runtime
    return runtime.path_metrics(runtime.AnytimeRunner(model_dir, warmup=False), frames)


def quantize_export(model_dir: Path, data: str, calibration_frames: int = 32, eval_frames: int = 64,
                    max_degradation: float = MAX_DEGRADATION, force: bool = False,
                    progress: Callable[[str], None] | None = None) -> dict:
    """Turns the fp32 export in ``model_dir`` (a scratch folder) into an int8 one in place and returns
    what the manifest records: per-path metrics before and after on ``eval_frames`` validation frames,
    each path's RMSE degradation, the calibration. Refuses (UserError) when a path degrades by more than
    ``max_degradation`` unless ``force``."""
    import json
    from explorer.runtime import MANIFEST
    if calibration_frames < 1 or eval_frames < 1:
        raise UserError("--calibration-frames and --eval-frames must be at least 1")
    if not 0 <= max_degradation:
        raise UserError(f"--max-degradation must be 0 or more, got {max_degradation}")
    manifest = json.loads((model_dir / MANIFEST).read_text())
    size = tuple(manifest["input_size"])
    say = progress or (lambda _: None)
    say(f"calibrating on {calibration_frames} training frames of {data}")
    calib = stage_inputs(model_dir, _frames(data, size, calibration_frames, "train"))
    evaluation = _frames(data, size, eval_frames, "val")
    say(f"measuring the fp32 paths on {len(evaluation)} validation frames")
    before = path_metrics(model_dir, evaluation)
    quantized = []
    for k, stage in enumerate(manifest["stages"]):
        say(f"quantizing {stage['file']}")
        src = model_dir / stage["file"]
        dst = src.with_name(src.stem + ".int8.onnx")
        if quantize_graph(src, dst, calib[k]):
            quantized.append(stage["file"])
        src.unlink()
        stage["file"] = dst.name
    (model_dir / MANIFEST).write_text(json.dumps(manifest, indent=2))
    say(f"measuring the int8 paths on {len(evaluation)} validation frames")
    after = path_metrics(model_dir, evaluation)
    degradation = [a["rmse"] / b["rmse"] - 1 if b["rmse"] > 0 else 0.0 for a, b in zip(after, before)]
    worst = int(np.argmax(degradation))
    if degradation[worst] > max_degradation and not force:
        raise UserError(f"int8 degrades path {worst}'s RMSE by {degradation[worst]:.1%} (> --max-degradation "
                        f"{max_degradation:.0%}; {before[worst]['rmse']:.4f} -> {after[worst]['rmse']:.4f} m): "
                        "not exported; keep fp32, calibrate on more frames, or add --force")
    return {"precision": "int8", "stages": manifest["stages"], "path_metrics_fp32": before, "path_metrics_int8": after,
            "quantization": {"method": "onnxruntime static QDQ: int8 weights per channel (7-bit range), uint8 "
                                       "activations (MinMax calibration), ops " + ", ".join(QUANTIZED_OPS)
                                       + f"; ungrouped convolutions of at least {MIN_INT8_REDUCTION} products per "
                                       "output only (depthwise and thinner ones stay float)",
                             "calibration": {"data": data, "split": "train", "frames": len(calib[0]) if calib else 0},
                             "evaluation": {"data": data, "split": "val", "frames": len(evaluation)},
                             "rmse_degradation": degradation, "max_degradation": max_degradation,
                             "forced": bool(force and degradation[worst] > max_degradation),
                             "quantized_graphs": quantized}}


def quantization_effect(net, input_size: tuple[int, int], data: str, calibration_frames: int = 16,
                        eval_frames: int = 32) -> dict:
    """How quantizing ``net``'s stage graphs to int8 changes each path's metrics, measured with
    onnxruntime on ``eval_frames`` validation frames of ``data`` (fp32 and int8 graphs alike): per
    path, each metric's int8 / fp32 ratio. What a search applies to an int8 candidate's estimate, so
    that it is compared with fp32 ones on the same frames."""
    import math
    from explorer.deploy import Quantization, export_network
    with tempfile.TemporaryDirectory(prefix="explorer-int8-") as tmp:
        m = export_network(net, Path(tmp) / "model", input_size, devices=(),
                           quantization=Quantization(data=data, calibration_frames=calibration_frames,
                                                     eval_frames=eval_frames, max_degradation=math.inf, force=True))
    before, after = m["path_metrics_fp32"], m["path_metrics_int8"]
    ratios = [{k: (a[k] / b[k] if b[k] else 1.0) for k in b if isinstance(b[k], (int, float))}
              for a, b in zip(after, before)]
    return {"ratios": ratios, "rmse_degradation": m["quantization"]["rmse_degradation"],
            "frames": m["quantization"]["evaluation"]["frames"]}


def _serve() -> None:
    """The worker's loop: (src, dst, feeds) in, (ok, quantized or error text) out, until stdin closes."""
    import os
    import pickle
    import sys
    channel = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)   # anything else printed goes to stderr, not into the answers
    while True:
        try:
            src, dst, feeds = pickle.load(sys.stdin.buffer)
        except EOFError:
            return
        try:
            answer = (True, _quantize(Path(src), Path(dst), feeds))
        except Exception as exc:   # sent back and raised in the parent
            answer = (False, f"{type(exc).__name__}: {exc}")
        pickle.dump(answer, channel)
        channel.flush()


if __name__ == "__main__":
    _serve()
