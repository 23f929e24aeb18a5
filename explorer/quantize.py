"""int8 deployment: an exported model's stage graphs quantized statically with onnxruntime
(QDQ format: int8 weights per output channel, uint8 activations whose ranges are calibrated on
frames of a data set), and every path's metrics measured again after quantization.

Each stage graph is calibrated on the inputs it really receives: the float model runs the
calibration frames and every stage's inputs are kept. A stage graph is quantized whole: every operator
onnxruntime's quantizer handles (convolutions of every kind, resizes, additions, concatenations), so
that its tensors stay uint8 from one layer to the next and it quantizes and dequantizes only at its
edges; only the LiDAR encoder stays fp32 (``FLOAT_STAGES``). Quantizing only the wide convolutions,
with float depthwise layers between them, paid for nothing: on this project's AVX-512 VNNI VM the
encoder stage ran 1.04x its fp32 speed that way and 1.68x quantized whole
(benchmarks/bench_runtime.py). The decoder stays channels-last, as onnxruntime runs quantized
convolutions: its nearest up-sampling becomes a uint8 copy done so (``upsamples_channels_last``; a
Resize left to onnxruntime is kept channels-first, ``resizes_kept_nchw``, its channels-last uint8
kernel being 30x slower) and its skip additions add so (``probe_script.channels_last_skip_adds``).
Whole quantization does not pay everywhere: on the Zen 4 VM the full-resolution decoders 3-4 ran no
faster in int8 alone (onnxruntime's uint8 depthwise kernels are slower than its blocked fp32 ones).
So an export keeps a stage int8 only
where int8 saves the staged runtime at least ``1 - INT8_KEEP_RATIO`` of that stage's fp32 time on the
exporting machine, with int8 neighbours handing each other uint8 tensors (``compare_speed``;
``stages="all"``: every stage int8), and the cost model
prices an int8 candidate's stages the same way (``explorer.cost.devices``); then, where a path loses
more RMSE than the export allows, it gives graphs back to fp32 one by one. Path 0 (the scan) has
nothing to quantize.

Weights are quantized to 7 bits (``reduce_range``): x86 CPUs without VNNI multiply uint8 by int8 in
pairs summed into int16 (VPMADDUBSW), which saturates with full-range weights; measured on one such
machine (AVX2), full range degraded the paper design's last path by 29% RMSE, 7 bits by under 2%.
"""

from __future__ import annotations

import contextlib
import io
import statistics
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from explorer.errors import UserError

#: a graph with none of these keeps fp32: nothing in it is worth quantizing
QUANTIZED_OPS = ["Conv", "ConvTranspose", "MatMul", "Gemm"]
#: an export keeps a stage int8 where it takes at most this fraction of its fp32 time (timing noise
#: would otherwise flip stages that int8 leaves as fast as they were)
INT8_KEEP_RATIO = 0.95
#: ``explorer export --int8-stages``: which stages of an int8 export are int8
INT8_STAGES = ("faster", "all")
#: Workload kinds an int8 stage graph runs quantized: every convolution (the rest, resizes and
#: additions, are quantized too, and priced by the int8 profile's fit of whole stage graphs).
QUANTIZABLE_KINDS = ("pointwise", "pointwise_1ch", "conv", "conv1d", "deconv", "depthwise")


#: Stages an int8 graph keeps fp32 around them. The LiDAR encoder reads the scan's metric depths,
#: which every path's scale rests on, and is 1-D and cheap. On the paper design (bench_runtime's net,
#: 64 frames, AMD EPYC AVX-512 VNNI), quantizing the encoders' graph whole lost 5.1% RMSE on the last
#: path (+6.7% on path 3); with the LiDAR encoder fp32, -0.7% (-0.1%), and the graph ran as fast
#: (2.28 against 2.27 ms; fp32 4.7-4.8 ms). Keeping the fusion unit or the exit head fp32 instead did
#: not help (+5.2%, +5.1%).
FLOAT_STAGES = ("lidar_encoder",)


def workload_quantized(w) -> bool:
    """Whether an int8 stage graph runs the cost-model ``Workload`` ``w`` as a quantized convolution
    (what the calibration times in int8 alone, besides whole graphs)."""
    return w.kind in QUANTIZABLE_KINDS and w.stage not in FLOAT_STAGES


def _float_nodes(model) -> list[str]:
    """The nodes of ``FLOAT_STAGES`` in an exported graph (torch names them /STAGE/...), and the
    exit heads' bilinear up-sampling (two matrix products with constant interpolation weights, which
    int8 would round: ``ops.Resize``)."""
    prefixes = tuple(f"/{s}/" for s in FLOAT_STAGES)
    return [n.name for n in model.graph.node
            if n.name.startswith(prefixes) or (n.op_type == "MatMul" and "/resize/" in n.name)]


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
    # the graphs' own inputs; one set of sessions: nothing here is timed
    runner = AnytimeRunner(model_dir, warmup=False, handoff=False, arenas="shared")
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


def _static_shapes(model) -> dict[str, list[int]]:
    """Each tensor's shape as onnx infers it, 0 for a dimension it cannot tell."""
    from onnx import shape_inference
    inferred = shape_inference.infer_shapes(model).graph
    return {v.name: [d.dim_value if d.HasField("dim_value") else 0 for d in v.type.tensor_type.shape.dim]
            for v in [*inferred.value_info, *inferred.output, *inferred.input]}


#: the identity Reshape ``resizes_kept_nchw`` puts after a nearest Resize
KEEP_NCHW_SUFFIX = "_keep_nchw"


def resizes_kept_nchw(model) -> int:
    """Puts an identity Reshape after every nearest Resize (the decoder's x2 up-sampling) of the float
    ``model`` (shapes inferred), in place; returns how many. onnxruntime runs a quantized graph's
    convolutions channels-last (NHWC) and carries that layout on through a uint8 Resize, whose
    channels-last kernel is slow (paper design, 16 channels to 224x224: 0.75 ms against 0.023 ms
    channels-first); it does not carry a layout through a Reshape, so the Resize stays channels-first.
    The paper design's int8 decoder graphs ran 1.2-1.6x faster so (each alone, 5 interleaved reps)."""
    from onnx import helper, numpy_helper
    shapes = _static_shapes(model)
    nodes, count = [], 0
    for node in model.graph.node:
        nodes.append(node)
        mode = next((a.s.decode() for a in node.attribute if a.name == "mode"), "nearest")
        shape = shapes.get(node.output[0]) if node.op_type == "Resize" and mode == "nearest" else None
        if not shape or 0 in shape:
            continue   # not a nearest Resize, or its output's shape is not static
        out = node.output[0]
        node.output[0] = out + "_nchw"
        model.graph.initializer.append(numpy_helper.from_array(np.array(shape, np.int64), out + "_shape"))
        nodes.append(helper.make_node("Reshape", [node.output[0], out + "_shape"], [out],
                                      name=node.name + KEEP_NCHW_SUFFIX))
        count += 1
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    return count


def _integer_factor(resize, shapes: dict[str, list[int]]) -> "tuple[list[int], int] | None":
    """(N, C, H, W) of a nearest ``resize``'s input and its integer up-sampling factor (the same for
    height and width), where the output repeats each input pixel so; else None."""
    from onnx import helper
    attrs = {a.name: helper.get_attribute_value(a) for a in resize.attribute}
    if (attrs.get("mode", b"nearest") != b"nearest" or attrs.get("antialias", 0)
            or attrs.get("coordinate_transformation_mode", b"half_pixel") not in (b"asymmetric", b"half_pixel")):
        return None
    # asymmetric + floor (what torch exports) and half_pixel + round_prefer_floor (the defaults) both
    # repeat each pixel f times for an integer factor f
    if attrs.get("nearest_mode", b"round_prefer_floor") != (
            b"floor" if attrs.get("coordinate_transformation_mode") == b"asymmetric" else b"round_prefer_floor"):
        return None
    src, dst = shapes.get(resize.input[0]), shapes.get(resize.output[0])
    if not src or not dst or len(src) != 4 or len(dst) != 4 or 0 in src or 0 in dst or src[:2] != dst[:2]:
        return None
    factor = dst[2] // src[2]
    if factor < 2 or dst[2] != factor * src[2] or dst[3] != factor * src[3]:
        return None
    return src, factor


#: the suffix of the nodes ``upsamples_channels_last`` makes
CHANNELS_LAST_UPSAMPLE_SUFFIX = "_channels_last_upsample"


def upsamples_channels_last(model) -> int:
    """Replaces each quantized nearest up-sampling by an integer factor (DequantizeLinear, Resize,
    QuantizeLinear with the same scale and zero point, and the identity Reshape ``resizes_kept_nchw``
    put after it, quantized the same way) by the same copy done on the uint8 tensor channels-last, in
    place; returns how many. onnxruntime runs the quantized convolutions channels-last and transposes
    their outputs channels-first for a Resize kept there (its channels-last uint8 Resize is slower
    still) and back after it; copied channels-last (two Concats of ``factor`` copies, each followed by a
    Reshape, between a Transpose pair that cancels against onnxruntime's own), the tensor never
    leaves that layout. A Concat of uint8 tensors is a plain copy; quantized (QLinearConcat), it saved
    little (decoders 3-4 of the paper design, one micro-benchmark: 0.633 against 0.676 ms; uint8 copies
    0.588 against 0.658 ms)."""
    from onnx import helper, numpy_helper
    from explorer._layout import _same_constant
    graph = model.graph
    shapes = _static_shapes(model)
    made = {o: n for n in graph.node for o in n.output}
    outputs = {o.name for o in graph.output}

    def only_reader(name: str, op_type: str):
        readers = [n for n in graph.node if name in n.input]
        if name in outputs or len(readers) != 1 or readers[0].op_type != op_type:
            return None
        return readers[0]

    def same_scale(node, dq) -> bool:
        return len(node.input) == 3 and all(a == b or _same_constant(graph, a, graph, b)
                                            for a, b in zip(node.input[1:], dq.input[1:]))

    replaced: dict[int, list] = {}
    dropped: set[int] = set()
    for resize in [n for n in graph.node if n.op_type == "Resize"]:
        dq, shape = made.get(resize.input[0]), _integer_factor(resize, shapes)
        q = only_reader(resize.output[0], "QuantizeLinear")
        if dq is None or dq.op_type != "DequantizeLinear" or len(dq.input) != 3 or not shape or q is None \
                or not same_scale(q, dq):
            continue
        span = [resize, q]   # the nodes from the Resize to the last QuantizeLinear
        dq2 = only_reader(q.output[0], "DequantizeLinear")
        reshape = dq2 and only_reader(dq2.output[0], "Reshape")
        q2 = (reshape and reshape.name.endswith(KEEP_NCHW_SUFFIX)
              and only_reader(reshape.output[0], "QuantizeLinear"))
        if q2 and same_scale(dq2, dq) and same_scale(q2, dq):
            span += [dq2, reshape, q2]
        (n, c, h, w), f = shape
        out = span[-1].output[0]
        name = resize.name + CHANNELS_LAST_UPSAMPLE_SUFFIX

        def const(suffix: str, value: list[int]) -> str:
            graph.initializer.append(numpy_helper.from_array(np.array(value, np.int64), name + suffix))
            return name + suffix
        replaced[id(span[-1])] = [
            helper.make_node("Transpose", [dq.input[0]], [name + "_nhwc"], perm=[0, 2, 3, 1], name=name + "_nhwc"),
            helper.make_node("Concat", [name + "_nhwc"] * f, [name + "_wide"], axis=3, name=name + "_wide"),
            helper.make_node("Reshape", [name + "_wide", const("_wide_shape", [n, h, f * w, c])], [name + "_w"],
                             name=name + "_w"),
            helper.make_node("Concat", [name + "_w"] * f, [name + "_tall"], axis=2, name=name + "_tall"),
            helper.make_node("Reshape", [name + "_tall", const("_shape", [n, f * h, f * w, c])], [name + "_hw"],
                             name=name + "_hw"),
            helper.make_node("Transpose", [name + "_hw"], [out], perm=[0, 3, 1, 2], name=name + "_nchw")]
        dropped |= {id(node) for node in span}
        if all(id(r) in dropped or r is resize for r in graph.node if dq.output[0] in r.input) \
                and dq.output[0] not in outputs:
            dropped.add(id(dq))
    if not replaced:
        return 0
    nodes = []
    for node in graph.node:
        nodes += replaced.get(id(node), [])
        if id(node) not in dropped:
            nodes.append(node)
    del graph.node[:]
    graph.node.extend(nodes)
    return len(replaced)


def pads_kept_uint8(model) -> int:
    """Makes every zero Pad between a DequantizeLinear and a QuantizeLinear of the same scale and zero
    point pad the uint8 tensor with its zero point instead, in place; returns how many. The quantizer
    leaves such a Pad float (the decoder's widening of a narrower skip: the paper design pads 256
    channels to 768), and onnxruntime then dequantizes, pads and quantizes three times the skip's
    size: 0.27 ms of the int8 decoder 1's 1.06 ms on the AVX-512 VNNI VM (onnxruntime's profiler)."""
    from onnx import helper, numpy_helper
    from explorer._layout import _same_constant
    graph = model.graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    made = {o: n for n in graph.node for o in n.output}

    def same(a: str, b: str) -> bool:
        return a == b or _same_constant(graph, a, graph, b)

    count = 0
    for pad in [n for n in graph.node if n.op_type == "Pad"]:
        mode = next((helper.get_attribute_value(a) for a in pad.attribute if a.name == "mode"), b"constant")
        dq = made.get(pad.input[0])
        value = pad.input[2] if len(pad.input) > 2 else ""
        readers = [n for n in graph.node if pad.output[0] in n.input]
        if (mode != b"constant" or dq is None or dq.op_type != "DequantizeLinear" or len(dq.input) < 3
                or (value and not (value in inits and not inits[value].any())) or len(pad.input) > 3
                or pad.output[0] in {o.name for o in graph.output} or not readers
                or not all(r.op_type == "QuantizeLinear" and len(r.input) == 3 and same(r.input[1], dq.input[1])
                           and same(r.input[2], dq.input[2]) for r in readers)
                or dq.input[2] not in inits):
            continue
        zero = pad.name + "_zero_point"
        graph.initializer.append(numpy_helper.from_array(inits[dq.input[2]].reshape(()), zero))
        pad.input[0] = dq.input[0]
        del pad.input[2:]
        pad.input.append(zero)
        quantized = readers[0].output[0]
        for r in readers:
            graph.node.remove(r)
            for n in graph.node:
                for k, name in enumerate(n.input):
                    if name == r.output[0]:
                        n.input[k] = quantized
        pad.output[0] = quantized
        if not any(dq.output[0] in n.input for n in graph.node):
            graph.node.remove(dq)
        count += 1
    return count


def _quantize(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process
    if not any(n.op_type in QUANTIZED_OPS for n in onnx.load(str(src)).graph.node):
        dst.write_bytes(src.read_bytes())
        return False
    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(src), str(prepared), skip_symbolic_shape=True)
        model = onnx.load(str(prepared))
        if resizes_kept_nchw(model):
            onnx.save(model, str(prepared))
        float_nodes = _float_nodes(model)
        # op_types_to_quantize left out: every operator the quantizer handles. Activation ranges from
        # the 99.999th percentile, not the extremes: on the paper design (32 and 128 calibration
        # frames) the last path lost 1.7-1.8% RMSE against 2.3-2.4% with min / max ranges
        def quantize(method: CalibrationMethod) -> None:
            # its calibrator prints five lines per graph ("Collecting tensor data ...") into the
            # terminal's progress bars: hundreds of lines for one calibration bundle
            with contextlib.redirect_stdout(io.StringIO()):
                quantize_static(str(prepared), str(dst), _Feeds(feeds), quant_format=QuantFormat.QDQ,
                                activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                                reduce_range=True, calibrate_method=method, nodes_to_exclude=float_nodes)
        try:
            quantize(CalibrationMethod.Percentile)
        except ValueError as exc:
            # the percentile calibrator's 2048-bin histogram fails on a tensor whose values all but agree
            # (seen: 2.50000-2.50004 m, an untrained exit head at its initial bias); min / max ranges take it
            if "bins" not in str(exc):
                raise
            quantize(CalibrationMethod.MinMax)
    model = onnx.load(str(dst))
    if pads_kept_uint8(model) + upsamples_channels_last(model):
        onnx.save(model, str(dst))
    return True


def share_edge_scales(graphs: list[Path]) -> int:
    """Gives every quantized stage graph in ``graphs`` (files, rewritten in place) the scale and zero
    point with which the graph that makes an input of it quantizes that tensor; returns how many inputs
    changed. Both are calibrated on the same values, but a reader that first slices a skip quantizes
    the slice with its own range. With one scale on both sides, the dequantize at the producer's end and
    the quantize at the reader's cancel exactly, and the runtime hands the uint8 tensor over
    (``explorer._layout.hand_off_quantized``). Done before an export measures its int8 paths."""
    import onnx
    models = [onnx.load(str(p)) for p in graphs]
    changed = _share_edge_scales(models)
    for k in changed:
        onnx.save(models[k], str(graphs[k]))
    return sum(changed.values())


def _dequantized_outputs(models) -> dict[str, tuple[int, object]]:
    """Tensor -> (index of the model that outputs it through a DequantizeLinear, that node)."""
    out = {}
    for k, model in enumerate(models):
        inits = {i.name for i in model.graph.initializer}
        outs = {o.name for o in model.graph.output}
        for n in model.graph.node:
            if (n.op_type == "DequantizeLinear" and n.output[0] in outs and len(n.input) == 3
                    and n.input[1] in inits and n.input[2] in inits):
                out[n.output[0]] = (k, n)
    return out


def _share_edge_scales(models) -> dict[int, int]:
    """``share_edge_scales`` on models in memory: {model index: inputs changed} for those changed."""
    from onnx import numpy_helper
    made = {}
    for name, (k, dq) in _dequantized_outputs(models).items():
        inits = {i.name: i for i in models[k].graph.initializer}
        made[name] = tuple(numpy_helper.to_array(inits[p]) for p in dq.input[1:3])
    changed: dict[int, int] = {}
    for k, model in enumerate(models):
        graph = model.graph
        inits = {i.name: i for i in graph.initializer}
        for name in (i.name for i in graph.input):
            if name not in made:
                continue
            quantizers = []
            for r in (n for n in graph.node if name in n.input):
                if r.op_type == "QuantizeLinear":
                    quantizers.append(r)
                elif r.op_type in ("Slice", "Reshape", "Squeeze", "Unsqueeze"):   # moves values, keeps them
                    quantizers += [n for n in graph.node if r.output[0] in n.input and n.op_type == "QuantizeLinear"]
            aligned = False
            for q in quantizers:
                for value, param in zip(made[name], q.input[1:3]):
                    old = inits.get(param)
                    if old is None:
                        continue
                    was = numpy_helper.to_array(old)
                    if was.shape != value.shape or was.dtype != value.dtype or (was == value).all():
                        continue
                    old.CopyFrom(numpy_helper.from_array(value, param))
                    aligned = True
            if aligned:
                changed[k] = changed.get(k, 0) + 1
    return changed


def uint8_edges(models) -> list[str]:
    """Rewrites quantized stage graphs (ModelProtos in run order, ``share_edge_scales`` done) so that a
    tensor that one dequantizes to output and every reader quantizes again at once with the same scale
    and zero point (or slices first, then quantizes) passes as uint8 under its own name; returns those
    names. What the runtime makes of an int8 export on a CPU (``explorer._layout.hand_off_quantized``),
    before onnxruntime's layout changes: the calibration bundle times int8 graphs so, as the runtime
    runs them."""
    from onnx import TensorProto
    from explorer._layout import _same_constant
    done = []
    for name, (p, dq) in _dequantized_outputs(models).items():
        src = models[p].graph

        def quantizes_alike(graph, node, tensor: str) -> bool:
            return (node.op_type == "QuantizeLinear" and len(node.input) == 3 and node.input[0] == tensor
                    and all(_same_constant(graph, q, src, d) for q, d in zip(node.input[1:3], dq.input[1:3])))

        plans = []   # per reading model: (graph, [(quantize node to drop, the tensor its output becomes)])
        for m in models:
            if m is models[p] or not any(i.name == name for i in m.graph.input):
                continue
            drops, graph = [], m.graph
            for r in [n for n in graph.node if name in n.input]:
                if quantizes_alike(graph, r, name):
                    drops.append((r, name))
                    continue
                after = [n for n in graph.node if r.output[0] in n.input]
                if (r.op_type not in ("Slice", "Reshape", "Squeeze", "Unsqueeze") or r.input[0] != name
                        or not after or not all(quantizes_alike(graph, n, r.output[0]) for n in after)):
                    drops = None
                    break
                drops += [(n, r.output[0]) for n in after]   # moves uint8 values as well as float ones
            if not drops:
                break
            plans.append((graph, drops))
        else:
            if not plans:
                continue
            quantized, float_name = dq.input[0], name + "_dequantized"
            for node in src.node:   # the uint8 tensor takes the name; the producer's readers keep the float one
                node.input[:] = [float_name if x == name else name if x == quantized else x for x in node.input]
                node.output[:] = [name if x == quantized else x for x in node.output]
            dq.output[0] = float_name
            if not any(float_name in n.input for n in src.node):
                src.node.remove(dq)
            next(o for o in src.output if o.name == name).type.tensor_type.elem_type = TensorProto.UINT8
            for graph, drops in plans:
                for q, becomes in drops:
                    graph.node.remove(q)
                    for node in graph.node:
                        node.input[:] = [becomes if x == q.output[0] else x for x in node.input]
                retyped = {becomes for _, becomes in drops}   # now uint8: shape inference's float entries go
                kept = [v for v in graph.value_info if v.name not in retyped]
                del graph.value_info[:]
                graph.value_info.extend(kept)
                next(i for i in graph.input if i.name == name).type.tensor_type.elem_type = TensorProto.UINT8
            done.append(name)
    return done


def compare_speed(model_dir: Path, manifest: dict, configs: list[dict[int, str]], frame: dict,
                  reps: int = 5) -> list[tuple[float, dict[int, float]]]:
    """For each of ``configs`` (stage index -> its int8 graph in ``model_dir``; the others fp32), the
    staged runtime's median ms on ``frame`` over its stage graphs, and each stage's own median ms within
    it. Timed in the chain, not graph by graph: int8 neighbours hand each other uint8 tensors
    (``explorer._layout.hand_off_quantized``), so a stage's precision changes what its neighbours pay
    too. The runners take turns, ``reps`` blocks of 5 timed runs each (``probe_script.time_chain``).
    Leaves the manifest as it was."""
    import json
    from explorer.cost.probe_script import chain_runs, time_chain
    from explorer.runtime import MANIFEST, AnytimeRunner
    kept = (model_dir / MANIFEST).read_text()
    runners = []
    try:
        for chosen in configs:
            files = [{**st, "file": chosen.get(k, st["file"])} for k, st in enumerate(manifest["stages"])]
            (model_dir / MANIFEST).write_text(json.dumps({**manifest, "stages": files}))
            runners.append(AnytimeRunner(model_dir, arenas="shared"))
    finally:
        (model_dir / MANIFEST).write_text(kept)
    image, scan = runners[0].check(frame["image"].numpy(), frame["scan"].numpy())
    chains = [chain_runs([sess for _, sess, _, _ in r.sessions], {"image": image, "scan": scan}) for r in runners]
    blocks: list[list[list[float]]] = [[] for _ in runners]   # per runner, per block: each stage's median ms
    for _ in range(reps):
        for (runs, new_round), per_block in zip(chains, blocks):
            # one untimed round first: the other runner's buffers were in the caches
            per_block.append(time_chain(runs, 1, 5, new_round=new_round))
    return [(statistics.median(map(sum, per_block)), {k: statistics.median(t) for k, t in enumerate(zip(*per_block))})
            for per_block in blocks]


def path_metrics(model_dir: Path, frames: list[dict]) -> list[dict[str, float]]:
    """Per-path metrics of the export in ``model_dir`` as its graphs stand now (fp32 or int8)."""
    from explorer import runtime
    return runtime.path_metrics(runtime.AnytimeRunner(model_dir, warmup=False, arenas="shared"), frames)


def quantize_export(model_dir: Path, data: str, calibration_frames: int = 32, eval_frames: int = 64,
                    max_degradation: float = MAX_DEGRADATION, force: bool = False,
                    progress: Callable[[str], None] | None = None,
                    stages: "str | tuple[str, ...]" = "faster") -> dict:
    """Turns the fp32 export in ``model_dir`` (a scratch folder) into an int8 one in place and returns
    what the manifest records: which stage graphs are int8 and why (``stages="faster"``: those whose int8
    saved the staged runtime at least ``1 - INT8_KEEP_RATIO`` of their fp32 time here; ``"all"``: every
    one; a tuple: those named, as
    ``CandidateCost.int8_graphs`` names the ones a device profile prices int8), per-path metrics before and after
    on ``eval_frames`` validation frames, each path's RMSE degradation, the calibration. Refuses
    (UserError) when a path degrades by more than ``max_degradation`` unless ``force``; with
    ``"faster"``, only once keeping graphs fp32 one by one (``kept_fp32_for_accuracy``) has not brought
    every path within it while one graph is still int8."""
    import json
    from explorer.runtime import MANIFEST, _is_scan_path
    if calibration_frames < 1 or eval_frames < 1:
        raise UserError("--calibration-frames and --eval-frames must be at least 1")
    if not 0 <= max_degradation:
        raise UserError(f"--max-degradation must be 0 or more, got {max_degradation}")
    if isinstance(stages, str) and stages not in INT8_STAGES:
        raise UserError(f"--int8-stages {stages}: use {' or '.join(INT8_STAGES)}")
    manifest = json.loads((model_dir / MANIFEST).read_text())
    size = tuple(manifest["input_size"])
    say = progress or (lambda _: None)
    say(f"calibrating on {calibration_frames} training frames of {data}")
    frames = _frames(data, size, calibration_frames, "train")
    calib = stage_inputs(model_dir, frames)
    evaluation = _frames(data, size, eval_frames, "val")
    say(f"measuring the fp32 paths on {len(evaluation)} validation frames")
    before = path_metrics(model_dir, evaluation)
    made: dict[int, Path] = {}   # stage index -> its int8 graph
    for k, stage in enumerate(manifest["stages"]):
        src = model_dir / stage["file"]
        dst = src.with_name(src.stem + ".int8.onnx")
        stage["precision"] = "fp32"
        if _is_scan_path(stage):
            continue   # the scan's own map: nothing to quantize
        if not isinstance(stages, str) and stage["name"] not in stages:
            continue
        say(f"quantizing {stage['file']}")
        if quantize_graph(src, dst, calib[k]):
            made[k] = dst
        else:
            dst.unlink(missing_ok=True)
    share_edge_scales(list(made.values()))
    int8_files = {k: dst.name for k, dst in made.items()}
    if stages == "faster" and made:
        # from every quantized stage int8, each in turn goes back to fp32 unless int8 saves the staged
        # runtime at least 1 - INT8_KEEP_RATIO of that stage's fp32 time
        say("timing the staged runtime with each quantized stage int8 and fp32")
        for k in list(made):
            stage = manifest["stages"][k]
            (with_ms, with_stages), (without_ms, without_stages) = compare_speed(
                model_dir, manifest, [int8_files, {j: f for j, f in int8_files.items() if j != k}], frames[0])
            fp32_ms, int8_ms = without_stages[k], with_stages[k]
            keep = with_ms <= without_ms - (1 - INT8_KEEP_RATIO) * fp32_ms
            stage["ms_here"] = {"fp32": round(fp32_ms, 4), "int8": round(int8_ms, 4),
                                "staged_fp32": round(without_ms, 4), "staged_int8": round(with_ms, 4)}
            say(f"  {stage['name']}: staged runtime {with_ms:.2f} ms with it int8, {without_ms:.2f} ms with it fp32 "
                "on this machine: " + ("int8" if keep else "kept fp32"))
            if not keep:
                (model_dir / int8_files.pop(k)).unlink()

    def choose(chosen: dict[int, str]) -> None:
        for k, stage in enumerate(manifest["stages"]):
            stage["precision"] = "int8" if k in chosen else "fp32"

    def measure(chosen: dict[int, str]) -> tuple[list[dict[str, float]], list[float]]:
        """Per-path metrics and RMSE degradation with exactly the graphs ``chosen`` int8."""
        choose(chosen)
        files = [{**st, "file": chosen.get(k, st["file"])} for k, st in enumerate(manifest["stages"])]
        (model_dir / MANIFEST).write_text(json.dumps({**manifest, "stages": files}, indent=2))
        after = path_metrics(model_dir, evaluation)
        return after, [a["rmse"] / b["rmse"] - 1 if b["rmse"] > 0 else 0.0 for a, b in zip(after, before)]

    say(f"measuring the int8 paths on {len(evaluation)} validation frames")
    after, degradation = measure(int8_files)
    kept_for_accuracy = []
    if stages == "faster" and not force:
        # over the limit: give back, one at a time, the int8 graph whose fp32 return helps the worst
        # path most (then the one that saved least time), while any int8 graph is left
        while len(int8_files) > 1 and max(degradation) > max_degradation:
            trials = []
            for k in int8_files:
                a, d = measure({j: f for j, f in int8_files.items() if j != k})
                saved = manifest["stages"][k].get("ms_here", {})
                trials.append((max(d), saved.get("fp32", 0.0) - saved.get("int8", 0.0), k, a, d))
            worst_after, _, k, after, degradation = min(trials, key=lambda t: t[:2])
            name = manifest["stages"][k]["name"]
            say(f"  {name} kept fp32: with it int8 a path lost more than {max_degradation:.1%} RMSE "
                f"(worst path without it {worst_after:+.1%})")
            kept_for_accuracy.append(name)
            (model_dir / int8_files.pop(k)).unlink()
        choose(int8_files)
    worst = int(np.argmax(degradation))
    if degradation[worst] > max_degradation and not force:
        last = manifest["stages"][next(iter(int8_files))]["name"] if kept_for_accuracy else None
        alone = f" even with only {last} int8" if last else ""
        raise UserError(f"int8 degrades path {worst}'s RMSE by {degradation[worst]:.1%}{alone} (> --max-degradation "
                        f"{max_degradation:.0%}; {before[worst]['rmse']:.4f} -> {after[worst]['rmse']:.4f} m): "
                        "not exported; keep fp32, calibrate on more frames, or add --force")
    quantized = []
    for k, stage in enumerate(manifest["stages"]):
        if k in int8_files:
            (model_dir / stage["file"]).unlink()
            quantized.append(stage["file"])
            stage["file"] = int8_files[k]
    (model_dir / MANIFEST).write_text(json.dumps(manifest, indent=2))
    return {"precision": "int8", "stages": manifest["stages"], "path_metrics_fp32": before, "path_metrics_int8": after,
            "quantization": {"method": "onnxruntime static QDQ, each stage graph quantized whole (every operator "
                                       "the quantizer handles): int8 weights per channel (7-bit range), uint8 "
                                       "activations (ranges at the 99.999th percentile of the calibration frames)",
                             "int8_stages": _why(stages),
                             "calibration": {"data": data, "split": "train", "frames": len(calib[0]) if calib else 0},
                             "evaluation": {"data": data, "split": "val", "frames": len(evaluation)},
                             "rmse_degradation": degradation, "max_degradation": max_degradation,
                             "forced": bool(force and degradation[worst] > max_degradation),
                             "quantized_graphs": quantized, "kept_fp32_for_accuracy": kept_for_accuracy}}


def _why(stages: "str | tuple[str, ...]") -> str:
    if stages == "all":
        return "all"
    if stages == "faster":
        return (f"faster: int8 where it saved the staged runtime at least {1 - INT8_KEEP_RATIO:.0%} of that stage "
                "graph's fp32 time on the exporting machine (ms_here), and every path stayed within max_degradation")
    return "as searched: those the device profile prices faster in int8"


def quantization_effect(net, input_size: tuple[int, int], data: str, calibration_frames: int = 16,
                        eval_frames: int = 32, stages: "str | tuple[str, ...]" = "faster") -> dict:
    """How quantizing ``net``'s stage graphs to int8 (``stages``, as ``quantize_export`` reads it)
    changes each path's metrics, measured with onnxruntime on ``eval_frames`` validation frames of
    ``data`` (fp32 and int8 graphs alike): per path, each metric's int8 / fp32 ratio. What a search
    applies to an int8 candidate's estimate, so that it is compared with fp32 ones on the same frames."""
    import math
    from explorer.deploy import Quantization, export_network
    if stages == ():   # no graph int8 (none pays on the device): its fp32 metrics
        paths = net.candidate.num_paths
        return {"ratios": [{}] * paths, "rmse_degradation": [0.0] * paths, "frames": 0, "int8_graphs": []}
    with tempfile.TemporaryDirectory(prefix="explorer-int8-") as tmp:
        m = export_network(net, Path(tmp) / "model", input_size, devices=(),
                           quantization=Quantization(data=data, calibration_frames=calibration_frames,
                                                     eval_frames=eval_frames, max_degradation=math.inf, force=True,
                                                     stages=stages))
    before, after = m["path_metrics_fp32"], m["path_metrics_int8"]
    ratios = [{k: (a[k] / b[k] if b[k] else 1.0) for k in b if isinstance(b[k], (int, float))}
              for a, b in zip(after, before)]
    return {"ratios": ratios, "rmse_degradation": m["quantization"]["rmse_degradation"],
            "frames": m["quantization"]["evaluation"]["frames"],
            "int8_graphs": [s["name"] for s in m["stages"] if s["precision"] == "int8"]}


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
