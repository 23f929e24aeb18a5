"""Which layers int8 pays for on this machine: single-layer graphs of the paper design's kinds and
sizes, each timed in float and quantized as ``explorer export --quantize int8`` quantizes (static QDQ,
7-bit per-channel weights, uint8 activations, the quantize / dequantize at its input and output
included). An export quantizes whole stage graphs, where a layer pays these edges only at the graph's
own (``explorer.deploy.quantize``); this shows what each kind costs alone, which is what decides
where int8 stages are worth keeping.

    python benchmarks/bench_int8_layers.py [--reps 3] [--threads 2]

Every layer in both precisions is timed in each repetition, in an order that rotates between
repetitions.
"""

import os
import tempfile
from pathlib import Path

os.environ.setdefault("EXPLORER_ORT_POOL", "session")   # quantize_static makes sessions of its own

from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static  # noqa: E402

from explorer.calibration.measure import session, time_call  # noqa: E402
from explorer.calibration.sweep import SweepLayer, layer_graph  # noqa: E402
from explorer.deploy.int8_graphs import _Feeds  # noqa: E402

from harness import Bench, interleave  # noqa: E402

#: (figure key, label, layer): the paper design's layers at 224x224
LAYERS = [
    ("stem_224", "stem 3->32 3x3 s2 at 224x224", SweepLayer("conv", (3, 224, 224), 32, 3, 2)),
    ("dw3_112x32", "depthwise 3x3 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 3, 1)),
    ("dw3_14x512", "depthwise 3x3 at 14x14x512", SweepLayer("depthwise", (512, 14, 14), 512, 3, 1)),
    ("dw5_28x768", "depthwise 5x5 at 28x28x768", SweepLayer("depthwise", (768, 28, 28), 768, 5, 1)),
    ("dw5_112x32", "depthwise 5x5 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 5, 1)),
    ("pw16_8_224", "pointwise 16->8 at 224x224", SweepLayer("pointwise", (16, 224, 224), 8)),
    ("pw32_16_112", "pointwise 32->16 at 112x112", SweepLayer("pointwise", (32, 112, 112), 16)),
    ("pw64_128_56", "pointwise 64->128 at 56x56", SweepLayer("pointwise", (64, 56, 56), 128)),
    ("pw512_512_14", "pointwise 512->512 at 14x14", SweepLayer("pointwise", (512, 14, 14), 512)),
    ("pw768_64_28", "pointwise 768->64 at 28x28", SweepLayer("pointwise", (768, 28, 28), 64)),
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
    bench = Bench(__file__, "int8 against fp32 per layer kind", __doc__)
    ap = bench.parser()
    ap.add_argument("--threads", type=int, default=2)
    args = bench.parse_args(ap)
    calls = {}
    for key, label, layer in LAYERS:
        model, feeds, _ = layer_graph(layer)
        fp32, int8 = session(model, args.threads), session(quantized(model, feeds), args.threads)
        calls[f"{key}_fp32"] = lambda s=fp32, f=feeds: time_call(lambda: s.run(None, f), 3, 25)
        calls[f"{key}_int8"] = lambda s=int8, f=feeds: time_call(lambda: s.run(None, f), 3, 25)
        bench.figure(f"{key}_fp32_ms", f"{label} fp32", "ms", "lower")
        bench.figure(f"{key}_int8_ms", f"{label} int8", "ms", "lower")
        bench.figure(f"{key}_int8_over_fp32", f"{label} int8 / fp32 time", "x", "lower")
    bench.note(f"{args.threads} threads")
    for rep in bench.repetitions():
        ms = interleave(calls, rep)
        for key, *_ in LAYERS:
            bench.add(f"{key}_fp32_ms", ms[f"{key}_fp32"])
            bench.add(f"{key}_int8_ms", ms[f"{key}_int8"])
            bench.add(f"{key}_int8_over_fp32", ms[f"{key}_int8"] / ms[f"{key}_fp32"])
    bench.finish()
