"""Which layers int8 pays for on this machine: single-layer graphs of the paper design's kinds and
sizes, each timed in float and quantized as `explorer export --quantize int8` quantizes (static QDQ,
7-bit per-channel weights, uint8 activations, the quantize / dequantize at its input and output
included). An export quantizes whole stage graphs, where a layer pays these edges only at the graph's
own (`explorer.deploy.quantize`); this shows what each kind costs alone. Interleaved, --reps repetitions in one invocation; every repetition and the median.

    .venv/bin/python benchmarks/bench_int8_layers.py [--reps 3]
"""

import argparse
import os
import statistics
import tempfile
from pathlib import Path

os.environ.setdefault("EXPLORER_ORT_POOL", "session")   # quantize_static makes sessions of its own

from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static  # noqa: E402

from explorer.calibration.calibrate import SweepLayer, layer_graph  # noqa: E402
from explorer.calibration.measure import session, time_call  # noqa: E402
from explorer.deploy.int8_graphs import _Feeds  # noqa: E402

#: (label, layer): the paper design's layers at 224x224
LAYERS = [
    ("stem 3->32 3x3 s2 at 224x224", SweepLayer("conv", (3, 224, 224), 32, 3, 2)),
    ("depthwise 3x3 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 3, 1)),
    ("depthwise 3x3 at 14x14x512", SweepLayer("depthwise", (512, 14, 14), 512, 3, 1)),
    ("depthwise 5x5 at 28x28x768", SweepLayer("depthwise", (768, 28, 28), 768, 5, 1)),
    ("depthwise 5x5 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 5, 1)),
    ("pointwise 16->8 at 224x224", SweepLayer("pointwise", (16, 224, 224), 8)),
    ("pointwise 32->16 at 112x112", SweepLayer("pointwise", (32, 112, 112), 16)),
    ("pointwise 64->128 at 56x56", SweepLayer("pointwise", (64, 56, 56), 128)),
    ("pointwise 512->512 at 14x14", SweepLayer("pointwise", (512, 14, 14), 512)),
    ("pointwise 768->64 at 28x28", SweepLayer("pointwise", (768, 28, 28), 64)),
]


def quantized(model: bytes, feeds: dict) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "f.onnx", Path(tmp) / "q.onnx"
        src.write_bytes(model)
        quantize_static(str(src), str(dst), _Feeds([feeds]), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        reduce_range=True, calibrate_method=CalibrationMethod.MinMax)
        return dst.read_bytes()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    graphs = []
    for label, layer in LAYERS:
        model, feeds, _ = layer_graph(layer)
        fp32, int8 = session(model, args.threads), session(quantized(model, feeds), args.threads)
        graphs.append((label, feeds, fp32, int8))
    ratios: dict[str, list[float]] = {label: [] for label, *_ in graphs}
    times: dict[str, list[tuple[float, float]]] = {label: [] for label, *_ in graphs}
    for rep in range(args.reps):   # interleaved: every layer, both precisions, then again
        for label, feeds, fp32, int8 in graphs:
            f = time_call(lambda: fp32.run(None, feeds), 3, 25)
            q = time_call(lambda: int8.run(None, feeds), 3, 25)
            ratios[label].append(q / f)
            times[label].append((f, q))
    print(f"int8 time / fp32 time per layer ({args.threads} threads), {args.reps} reps")
    for label, *_ in graphs:
        r = ratios[label]
        f = statistics.median(t[0] for t in times[label])
        q = statistics.median(t[1] for t in times[label])
        print(f"  {label:32s} fp32 {f:.3f} ms, int8 {q:.3f} ms: "
              f"{statistics.median(r):.2f}x ({min(r):.2f}-{max(r):.2f}; reps {' '.join(f'{x:.2f}' for x in r)})")
