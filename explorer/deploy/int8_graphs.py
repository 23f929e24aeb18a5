"""int8 stage graphs: one graph quantized statically with onnxruntime (QDQ format: int8 weights per
output channel, uint8 activations calibrated on the inputs the stage really receives), and the rewrites
that keep a quantized decoder channels-last and hand uint8 tensors between int8 graphs.

Weights are quantized to 7 bits (``reduce_range``): x86 CPUs without VNNI multiply uint8 by int8 in
pairs summed into int16 (VPMADDUBSW), which saturates with full-range weights (the paper design's last
path lost far more RMSE with full-range weights than with 7 bits on such a machine).
"""


import contextlib
import io
from pathlib import Path

import numpy as np

from explorer.cost.precision import FLOAT_STAGES
from explorer.files import scratch_dir
from explorer.probe import same_constant, shared_pool_threads

#: a graph with none of these keeps fp32: nothing in it is worth quantizing
QUANTIZED_OPS = ["Conv", "ConvTranspose", "MatMul", "Gemm"]


def _float_nodes(model) -> list[str]:
    """The nodes of ``FLOAT_STAGES`` in an exported graph (torch names them /STAGE/...), and the
    exit heads' bilinear up-sampling (two matrix products with constant interpolation weights, which
    int8 would round: ``ops.Resize``)."""
    prefixes = tuple(f"/{s}/" for s in FLOAT_STAGES)
    return [n.name for n in model.graph.node
            if n.name.startswith(prefixes) or (n.op_type == "MatMul" and "/resize/" in n.name)]


class _Feeds:
    """onnxruntime.quantization's CalibrationDataReader over recorded stage inputs."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]) -> None:
        self._it = iter(feeds)

    def get_next(self):
        return next(self._it, None)


def quantize_graph(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    """Writes ``src`` quantized to ``dst``; False (and a plain copy) when it has nothing to quantize.
    onnxruntime.quantization makes sessions with thread pools of their own, which a process whose
    sessions share the global pool (``explorer.probe.session``) may not: there it runs in a child process."""
    if shared_pool_threads() is not None:
        return _quantize_in_child(Path(src), Path(dst), feeds)
    return _quantize(Path(src), Path(dst), feeds)


_WORKER: list = []   # one child process, started on first use and kept for the rest of this process


def _quantize_in_child(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]]) -> bool:
    """Sends the job to the worker (``python -m explorer.deploy.quantize``: pickles over its stdin and stdout)."""
    import pickle
    import subprocess
    import sys
    if not _WORKER or _WORKER[0].poll() is not None:
        _WORKER[:] = [subprocess.Popen([sys.executable, "-m", "explorer.deploy.int8_graphs"], stdin=subprocess.PIPE,
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
        return len(node.input) == 3 and all(a == b or same_constant(graph, a, graph, b)
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
    size: about a quarter of the int8 decoder 1's time, as onnxruntime's profiler shows."""
    from onnx import helper, numpy_helper
    graph = model.graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    made = {o: n for n in graph.node for o in n.output}

    def same(a: str, b: str) -> bool:
        return a == b or same_constant(graph, a, graph, b)

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
    from onnxruntime.quantization import (
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process
    if not any(n.op_type in QUANTIZED_OPS for n in onnx.load(str(src)).graph.node):
        dst.write_bytes(src.read_bytes())
        return False
    with scratch_dir("quantize") as tmp:
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
    (``explorer.probe.rewrites.hand_off_quantized``). Done before an export measures its int8 paths."""
    import onnx
    models = [onnx.load(str(p)) for p in graphs]
    changed = share_model_edge_scales(models)
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


def share_model_edge_scales(models) -> dict[int, int]:
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
    names. What the runtime makes of an int8 export on a CPU (``explorer.probe.rewrites.hand_off_quantized``),
    before onnxruntime's layout changes: the calibration bundle times int8 graphs so, as the runtime
    runs them."""
    from onnx import TensorProto
    done = []
    for name, (p, dq) in _dequantized_outputs(models).items():
        src = models[p].graph

        def quantizes_alike(graph, node, tensor: str) -> bool:
            return (node.op_type == "QuantizeLinear" and len(node.input) == 3 and node.input[0] == tensor
                    and all(same_constant(graph, q, src, d) for q, d in zip(node.input[1:3], dq.input[1:3])))

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

