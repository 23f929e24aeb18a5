"""Stage graphs that hand tensors to the next stage as onnxruntime holds them: fp32 ones in its
blocked channel layout (``hand_off_blocked``), ones that two int8 stages pass as uint8, channels-last
where both sides are (``hand_off_quantized``).

onnxruntime's CPU provider runs convolutions on channels blocked by its vector width (NCHWc) and
converts at a graph's edges. A tensor that one stage outputs and the next one reads (the decoder's
running feature map) leaves the first graph in plain NCHW and is converted into the blocked layout
again by the second, although the first had converted it already for its own exit head. On the paper
design at 224x224 those three extra conversions were half of the staged runtime's overhead over one
whole graph (+5.9% -> +2.8%, benchmarks/bench_runtime.py).

``hand_off_blocked`` rewrites the stage graphs after onnxruntime has optimised them on this machine: the
producing graph also outputs its blocked copy (``NAME.nchwc``) and the reading graph takes that in place
of its conversion. The encoder's skips go the same way, since each decoder adds its skip blocked
(``probe_script.blocked_skip_adds``): where the producer has a tensor blocked and converts it only to
output it, the blocked tensor is output instead and the conversion dropped.

An int8 stage graph dequantizes what it outputs, and an int8 reader quantizes it again at once and
transposes it channels-last for its convolutions; ``hand_off_quantized`` removes those pairs where
they cancel. The rewritten graphs hold this machine's block size and fused kernels, so a runner makes
them when it loads and never stores them.
"""

from __future__ import annotations

from onnx import ModelProto, TensorProto, helper

# in the probe script, which the calibration bundle carries: the probe hands tensors over blocked too
from explorer.cost.probe_script import (SUFFIX, _channels_last, _drop_unread, _read_instead, _rename,  # noqa: F401
                                       hand_off_blocked)

#: the suffixes of a tensor handed over quantized: plain (NCHW) and channels-last
UINT8_SUFFIX, UINT8_NHWC_SUFFIX = ".uint8", ".uint8_nhwc"


def _same_constant(a_graph, a: str, b_graph, b: str) -> bool:
    from onnx import numpy_helper
    ta = next((i for i in a_graph.initializer if i.name == a), None)
    tb = next((i for i in b_graph.initializer if i.name == b), None)
    if ta is None or tb is None:
        return False
    x, y = numpy_helper.to_array(ta), numpy_helper.to_array(tb)
    return x.dtype == y.dtype and x.shape == y.shape and bool((x == y).all())


def hand_off_quantized(models: list[ModelProto], inputs: list[list[str]], outputs: list[list[str]]) -> dict[str, str]:
    """Rewrites ``models`` (optimised stage graphs in run order) in place so that int8 stages hand each
    other uint8 tensors; returns ``{name: "uint8" or "uint8 nhwc"}`` for the tensors now handed so.

    An int8 stage dequantizes the tensor it outputs and the int8 stage that reads it quantizes it again
    at once. Where the reader quantizes with the producer's very scale and zero point (an export makes
    them so: ``explorer.quantize.share_edge_scales``), the pair is the identity and both nodes go: the
    producer outputs its uint8 tensor (``NAME.uint8``). Where, besides, the reader only transposes it
    channels-last (onnxruntime runs quantized convolutions so) and the producer made it by transposing
    its channels-last one, or transposes it so itself (for its exit head), the channels-last tensor is
    handed (``NAME.uint8_nhwc``). A
    conversion that no graph needs any more is dropped from its producer."""
    producer = {name: i for i, outs in enumerate(outputs) for name in outs}
    handed: dict[str, str] = {}
    for j, model in enumerate(models):
        graph = model.graph
        for name in inputs[j]:
            if name not in producer:
                continue
            src = models[producer[name]].graph
            dq = next((n for n in src.node if n.op_type == "DequantizeLinear" and list(n.output) == [name]), None)
            readers = [n for n in graph.node if name in n.input]
            if dq is None or len(dq.input) < 3 or not readers:
                continue
            if not all(n.op_type == "QuantizeLinear" and len(n.input) == 3 and list(n.input[:1]) == [name]
                       and _same_constant(graph, n.input[1], src, dq.input[1])
                       and _same_constant(graph, n.input[2], src, dq.input[2]) for n in readers):
                continue
            quantized = name + UINT8_SUFFIX
            if not any(o.name == quantized for o in src.output):
                _rename(src, dq.input[0], quantized)
                src.output.append(helper.make_tensor_value_info(quantized, TensorProto.UINT8, None))
            _read_instead(graph, readers, name, quantized, TensorProto.UINT8)
            handed[name] = "uint8"
            # channels-last: every reader transposes it so, and the producer made it from or makes it into that
            if _channels_last(src, graph, quantized, name + UINT8_NHWC_SUFFIX, TensorProto.UINT8):
                handed[name] = "uint8 nhwc"
    for name in handed:   # forms no graph reads any more: their outputs and the nodes that made them
        for form in (name, name + UINT8_SUFFIX):
            _drop_unread(models[producer[name]].graph, models, form)
    return handed
