"""Graph rewrites that the runtime and the probe share: the decoder's skip additions kept in
onnxruntime's blocked (NCHWc) or channels-last layout, and stage graphs that hand tensors over as
onnxruntime holds them (blocked fp32, or uint8 between int8 stages).

Stage graphs that hand tensors to the next stage as onnxruntime holds them: fp32 ones in its
blocked channel layout (``hand_off_blocked``), ones that two int8 stages pass as uint8, channels-last
where both sides are (``hand_off_quantized``).

onnxruntime's CPU provider runs convolutions on channels blocked by its vector width (NCHWc) and
converts at a graph's edges. A tensor that one stage outputs and the next one reads (the decoder's
running feature map) leaves the first graph in plain NCHW and is converted into the blocked layout
again by the second, although the first had converted it already for its own exit head. Those extra
conversions are a large part of the staged runtime's overhead over one whole graph.

``hand_off_blocked`` rewrites the stage graphs after onnxruntime has optimised them on this machine: the
producing graph also outputs its blocked copy (``NAME.nchwc``) and the reading graph takes that in place
of its conversion. The encoder's skips go the same way, since each decoder adds its skip blocked
(``blocked_skip_adds``): where the producer has a tensor blocked and converts it only to
output it, the blocked tensor is output instead and the conversion dropped.

An int8 stage graph dequantizes what it outputs, and an int8 reader quantizes it again at once and
transposes it channels-last for its convolutions; ``hand_off_quantized`` removes those pairs where
they cancel. The rewritten graphs hold this machine's block size and fused kernels, so a runner makes
them when it loads and never stores them.
"""

from __future__ import annotations


try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None

# -- the decoder's skip additions in the blocked layout ----------------------------------------
NCHWC_DOMAIN = "com.microsoft.nchwc"


def _onnx():
    """The onnx package, where this Python has it (the rewrite below needs it; the probe does not)."""
    try:
        import onnx
    except ImportError:
        return None
    return onnx


class _Graph:
    """Look-ups over an onnx graph that the skip-addition rewrites share: which node makes a tensor,
    which nodes read it, the integer constants. ``refresh`` after nodes are added or removed."""

    def __init__(self, graph) -> None:
        self.g = graph
        self.initializers = {i.name: i for i in graph.initializer}   # as the graph came: not add_const's
        self.inputs = {i.name: i for i in graph.input}
        self.refresh()

    def refresh(self) -> None:
        self.made_by = {o: n for n in self.g.node for o in n.output}

    def readers(self, name: str) -> list:
        return [n for n in self.g.node if name in n.input]

    def outputs(self) -> set[str]:
        return {o.name for o in self.g.output}

    def const(self, name: str) -> np.ndarray:
        from onnx import numpy_helper
        return numpy_helper.to_array(self.initializers[name])

    def ints(self, name: str) -> "list[int] | None":
        return [int(v) for v in self.const(name).reshape(-1)] if name in self.initializers else None

    def add_const(self, name: str, value: list[int]) -> str:
        from onnx import numpy_helper
        self.g.initializer.append(numpy_helper.from_array(np.array(value, np.int64), name))
        return name


def blocked_skip_adds(model, block: int) -> int:
    """Rewrites, in place, onnxruntime's optimised graph ``model`` so that each of the decoder's skip
    additions stays in the blocked (NCHWc) layout; returns how many it rewrote. ``block`` is
    onnxruntime's channel block on this machine (``sessions.block_size``).

    onnxruntime leaves the blocked layout around a skip addition: it converts the up-sampled decoder
    tensor and the skip to NCHW, slices (or zero-pads) the skip's channels to the decoder's width, adds,
    and converts the sum back. Where both widths are multiples of the block, the slice or pad acts on
    the blocked skip seen as (N, C / block, H x W, block), and two blocked tensors of one shape add
    element-wise, so none of the three conversions is needed (a skip that is a graph input, in a stage
    graph, is converted once, and the runtime then hands it over blocked). The paper design's whole
    graph at 224x224 runs faster so, on machines with AVX-512 and with AVX2 alike
    (bench_blocked_skip); the results are identical."""
    graph = _Graph(model.graph)
    done = 0
    for add in [n for n in model.graph.node if n.op_type == "Add" and n.domain == "" and len(n.input) == 2]:
        skip_add = _blocked_skip_add(graph, add, block)
        if skip_add is not None:
            _add_blocked(graph, skip_add, block)
            graph.refresh()
            done += 1
    if done:
        del model.graph.value_info[:]   # shapes onnxruntime inferred for tensors that are gone or now blocked
    return done


class _SkipAdd:
    """A skip addition that ``blocked_skip_adds`` can keep blocked: the addition, the conversion of
    the decoder side (``up``), the skip's slice or pad (``fit``), the skip, its readers (``after``)
    and both channel counts (``cx`` the decoder's, ``cs`` the skip's)."""

    def __init__(self, add, up, fit, skip: str, after: list, is_output: bool, cx: int, cs: int) -> None:
        self.add, self.up, self.fit, self.skip, self.after = add, up, fit, skip, after
        self.is_output, self.cx, self.cs = is_output, cx, cs


def _blocked_skip_add(graph: _Graph, add, block: int) -> "_SkipAdd | None":
    """``add`` as a skip addition to keep blocked: one side converted out of the blocked layout, the
    other a slice or pad of the skip, read only by blocked conversions (or a stage graph's output),
    and both widths multiples of ``block``; else None."""
    for up_name, fit_name in (add.input, reversed(add.input)):
        up, fit = graph.made_by.get(up_name), graph.made_by.get(fit_name)
        if up is not None and up.op_type == "ReorderOutput" and fit is not None and fit.op_type in ("Slice", "Pad"):
            break
    else:
        return None
    after = graph.readers(add.output[0])
    is_output = add.output[0] in graph.outputs()   # a stage graph's, for the next stage
    skip = fit.input[0]
    cx, cs = _channels(graph, up_name), _channels(graph, skip)
    if (len(after) > 1 or not (after or is_output) or any(n.op_type != "ReorderInput" for n in after)
            or not cx or not cs or len(graph.readers(fit.output[0])) != 1
            or not _fits_channels_only(graph, fit, cs, cx)):
        return None
    if cx % block or cs % block:
        return None
    return _SkipAdd(add, up, fit, skip, after, is_output, cx, cs)


def _channels(graph: _Graph, name: str) -> "int | None":
    """The channel count of ``name``: as its conversion out of the blocked layout records it, or its
    shape's where it is a 4-d graph input."""
    from onnx import helper
    node = graph.made_by.get(name)
    if node is not None and node.op_type == "ReorderOutput" and node.domain == NCHWC_DOMAIN:
        return next((helper.get_attribute_value(a) for a in node.attribute if a.name == "channels"), None)
    dims = graph.inputs[name].type.tensor_type.shape.dim if name in graph.inputs else []
    return dims[1].dim_value or None if len(dims) == 4 else None


def _fits_channels_only(graph: _Graph, fit, cs: int, cx: int) -> bool:
    """Whether ``fit`` only takes the skip's first ``cx`` channels, or pads it with zero channels."""
    from onnx import helper
    ints = graph.ints
    if fit.op_type == "Slice":   # skip[:, :cx]
        steps = ints(fit.input[4]) if len(fit.input) > 4 and fit.input[4] else [1]
        ends = ints(fit.input[2]) or [0]
        return (len(fit.input) > 3 and ints(fit.input[1]) == [0] and ints(fit.input[3]) == [1]
                and steps == [1] and min(ends[0], cs) == cx)
    pads = ints(fit.input[1]) if len(fit.input) > 1 else None
    zero = len(fit.input) < 3 or fit.input[2] == "" or ints(fit.input[2]) == [0]
    mode = next((helper.get_attribute_value(a) for a in fit.attribute if a.name == "mode"), b"constant")
    return (pads == [0, 0, 0, 0, 0, cx - cs, 0, 0] and zero and mode == b"constant"
            and (len(fit.input) < 4 or fit.input[3] == ""))


def _add_blocked(graph: _Graph, s: _SkipAdd, b: int) -> None:
    """Replaces the conversions, the slice or pad and the addition of ``s`` with a slice or pad of
    the blocked skip seen as (N, C / b, H x W, b) and an addition of the two blocked tensors."""
    from onnx import helper
    tag = s.add.output[0]
    skip_node = graph.made_by.get(s.skip)
    nodes = []
    if skip_node is not None and skip_node.op_type == "ReorderOutput":
        blocked_skip = skip_node.input[0]
    else:   # a graph input: converted here, once
        blocked_skip = tag + ".skip"
        nodes.append(helper.make_node("ReorderInput", [s.skip], [blocked_skip], domain=NCHWC_DOMAIN,
                                      channels_last=0))
    graph.add_const(tag + ".as5", [0, s.cs // b, -1, b])
    nodes.append(helper.make_node("Reshape", [blocked_skip, tag + ".as5"], [tag + ".s5"]))
    if s.fit.op_type == "Slice":
        for name, value in (("start", 0), ("end", s.cx // b), ("axis", 1)):
            graph.add_const(f"{tag}.{name}", [value])
        nodes.append(helper.make_node("Slice", [tag + ".s5", tag + ".start", tag + ".end", tag + ".axis"],
                                      [tag + ".fit5"]))
    else:
        graph.add_const(tag + ".pads", [0, 0, 0, 0, 0, (s.cx - s.cs) // b, 0, 0])
        nodes.append(helper.make_node("Pad", [tag + ".s5", tag + ".pads"], [tag + ".fit5"]))
    summed = s.after[0].output[0] if s.after else tag + ".blocked"
    nodes += [helper.make_node("Shape", [s.up.input[0]], [tag + ".shape"]),
              helper.make_node("Reshape", [tag + ".fit5", tag + ".shape"], [tag + ".fit"]),
              helper.make_node("Add", [s.up.input[0], tag + ".fit"], [summed])]
    if s.is_output:
        nodes.append(helper.make_node("ReorderOutput", [summed], [tag], domain=NCHWC_DOMAIN,
                                      channels_last=0, channels=s.cx))
    _splice(graph, s, skip_node, nodes, summed)


def _splice(graph: _Graph, s: _SkipAdd, skip_node, nodes: list, summed: str) -> None:
    """Removes what ``nodes`` replace (and conversions nothing reads any more) and inserts ``nodes``
    before the first node that reads their result."""
    g = graph.g
    for n in s.after + [s.add, s.fit]:
        g.node.remove(n)
    outputs = graph.outputs()
    for n in (s.up, skip_node):   # conversions nothing reads any more
        if n is not None and n.op_type == "ReorderOutput" and not graph.readers(n.output[0]) \
                and n.output[0] not in outputs:
            g.node.remove(n)
    at = next((k for k, n in enumerate(g.node) if summed in n.input or s.add.output[0] in n.input),
              len(g.node))   # before its readers
    for k, n in enumerate(nodes):
        g.node.insert(at + k, n)


def channels_last_skip_adds(model) -> int:
    """Rewrites, in place, onnxruntime's optimised graph ``model`` so that each quantized skip addition
    (QLinearAdd) whose decoder side is transposed channels-first only for it adds channels-last; returns
    how many it rewrote.

    onnxruntime runs quantized convolutions channels-last, but leaves a QLinearAdd channels-first: the
    up-sampled decoder tensor is transposed channels-first for the addition and the sum back for the
    next convolution (on the paper design's 768-channel decoder 1, about a quarter of the int8 stage).
    An addition is element-wise, so the skip is transposed channels-last instead (before
    its slice or zero pad to the decoder's width, which then act on the last axis), and the sum stays
    channels-last for the readers that transposed it so; the others get it transposed back. A skip that
    is a graph input is transposed where it enters, which the runtime's handoff removes where its
    producer made it channels-last (``hand_off_channels_last``). The results are identical."""
    graph = _Graph(model.graph)
    four_d = {i.name for i in model.graph.input if len(i.type.tensor_type.shape.dim) == 4}
    outputs = graph.outputs()
    done = 0
    for add in [n for n in model.graph.node if n.op_type == "QLinearAdd" and n.domain == "com.microsoft"]:
        sides = _transposed_side(graph, add)
        if sides is None:
            continue
        a, b, up = sides
        fit = graph.made_by.get(add.input[b])
        fit = fit if fit is not None and fit.op_type in ("Slice", "Pad") and fit.domain in ("", "ai.onnx") else None
        skip = fit.input[0] if fit is not None else add.input[b]
        made = graph.made_by.get(skip)
        quantized_input = made is not None and made.op_type == "QuantizeLinear" and made.input[0] in four_d
        if not (skip in four_d or quantized_input or (made is not None and _perm(made) == _TO_NCHW)):
            continue   # a skip of unknown rank: transposing it might break the broadcast
        if fit is not None:
            new_inputs = _fit_inputs_last(graph, fit, add.output[0], outputs)
            if new_inputs is None:
                continue
            del fit.input[:]
            fit.input.extend(new_inputs)
        _add_last(graph, add, a, b, up, fit, skip, made, outputs)
        graph.refresh()
        done += 1
    if done:
        del model.graph.value_info[:]   # shapes onnxruntime inferred for tensors now channels-last
    return done


def _transposed_side(graph: _Graph, add) -> "tuple[int, int, object] | None":
    """(index of the decoder input, index of the skip input, the transpose that made the decoder
    one channels-first) of the QLinearAdd ``add`` (inputs 0 and 3 are its two tensors), or None."""
    for a, b in ((0, 3), (3, 0)):
        up = graph.made_by.get(add.input[a])
        if up is not None and _perm(up) == _TO_NCHW:
            return a, b, up
    return None


def _fit_inputs_last(graph: _Graph, fit, tag: str, outputs: set[str]) -> "list[str] | None":
    """The inputs of the skip's slice or pad that make it act on a channels-last tensor (new axes or
    pads, added as constants named after ``tag``), or None where it cannot be moved: it has other
    readers, is an output, takes a computed input or pads other than 4-d."""
    to_last = lambda axes: [_TO_NHWC.index(int(a) % 4) for a in axes]  # noqa: E731
    if len(graph.readers(fit.output[0])) != 1 or fit.output[0] in outputs \
            or any(n and n not in graph.initializers for n in fit.input[1:]):
        return None
    if fit.op_type == "Slice":
        axes = (graph.const(fit.input[3]) if len(fit.input) > 3 and fit.input[3]
                else range(len(graph.const(fit.input[1]))))
        return list(fit.input[:3]) + [graph.add_const(tag + ".fit_axes", to_last(axes))] + list(fit.input[4:])
    if len(fit.input) > 3 and fit.input[3]:
        return list(fit.input[:3]) + [graph.add_const(tag + ".fit_axes", to_last(graph.const(fit.input[3])))]
    pads = [int(v) for v in graph.const(fit.input[1]).reshape(-1)]
    if len(pads) != 8:
        return None
    return [fit.input[0], graph.add_const(tag + ".fit_pads", [pads[p] for p in _TO_NHWC]
                                          + [pads[4 + p] for p in _TO_NHWC])] + list(fit.input[2:])


def _add_last(graph: _Graph, add, a: int, b: int, up, fit, skip: str, made, outputs: set[str]) -> None:
    """Makes ``add`` take the decoder tensor and the skip (through ``fit``, if any) channels-last and
    give its sum channels-last to the readers that transposed it so, channels-first to the rest."""
    from onnx import helper
    g = graph.g
    tag = add.output[0]
    at = list(g.node).index(fit if fit is not None else add)
    if made is not None and _perm(made) == _TO_NCHW:
        skip_last = made.input[0]
    else:
        skip_last = tag + ".skip_nhwc"
        g.node.insert(at, helper.make_node("Transpose", [skip], [skip_last], perm=_TO_NHWC, name=skip_last))
    if fit is not None:
        fit.input[0] = skip_last
    else:
        add.input[b] = skip_last
    add.input[a] = up.input[0]
    summed = tag + ".nhwc_sum"
    add.output[0] = summed
    for n in [n for n in graph.readers(tag) if _perm(n) == _TO_NHWC and n.output[0] not in outputs]:
        g.node.remove(n)
        _rename_input(g, n.output[0], summed)
    if graph.readers(tag) or tag in outputs:
        g.node.insert(list(g.node).index(add) + 1,
                      helper.make_node("Transpose", [summed], [tag], perm=_TO_NCHW, name=tag + ".nchw"))
    if not graph.readers(up.output[0]) and up.output[0] not in outputs:
        g.node.remove(up)


# -- stage graphs that hand tensors over blocked, as the runtime runs them ------------------------
SUFFIX = ".nchwc"


def _is_plain_reorder_in(node) -> bool:
    from onnx import helper
    channels_last = next((helper.get_attribute_value(a) for a in node.attribute if a.name == "channels_last"), 0)
    return node.op_type == "ReorderInput" and node.domain == NCHWC_DOMAIN and channels_last == 0


def _rename_input(graph, old: str, new: str) -> None:
    for node in graph.node:
        for k, name in enumerate(node.input):
            if name == old:
                node.input[k] = new


def _rename(graph, old: str, new: str) -> None:
    _rename_input(graph, old, new)
    for node in graph.node:
        for k, name in enumerate(node.output):
            if name == old:
                node.output[k] = new


def _read_instead(graph, dropped: list, old: str, new: str, elem_type: int) -> None:
    """``graph`` takes the input ``new`` in place of ``old`` and reads it where the ``dropped`` nodes'
    outputs were read."""
    from onnx import helper
    for node in dropped:
        graph.node.remove(node)
        _rename_input(graph, node.output[0], new)
    kept = [i for i in graph.input if i.name != old]
    del graph.input[:]
    graph.input.extend(kept)
    graph.input.append(helper.make_tensor_value_info(new, elem_type, None))


def hand_off_blocked(models: list, inputs: list[list[str]], outputs: list[list[str]]) -> list[str]:
    """Rewrites ``models`` (optimised stage graphs in run order; ``inputs`` and ``outputs``: the names
    each one reads and writes) in place; returns the names of the tensors now handed over blocked. A
    tensor is, when every node of its reader that reads it converts it to the blocked layout."""
    from onnx import TensorProto, helper
    producer = {name: i for i, outs in enumerate(outputs) for name in outs}
    handed = []
    for j, model in enumerate(models):
        graph = model.graph
        for name in inputs[j]:
            if name not in producer:
                continue
            readers = [n for n in graph.node if name in n.input]
            if not readers or not all(_is_plain_reorder_in(n) for n in readers):
                continue
            blocked = name + SUFFIX
            src = models[producer[name]].graph
            if not any(o.name == blocked for o in src.output):
                own = next((n for n in src.node if _is_plain_reorder_in(n) and list(n.input) == [name]), None)
                made = next((n for n in src.node if n.op_type == "ReorderOutput" and n.domain == NCHWC_DOMAIN
                             and list(n.output) == [name]), None)
                if own is not None:        # the producer converts it already (for its exit head)
                    _rename_input(src, own.output[0], blocked)
                    own.output[0] = blocked
                elif made is not None:     # the producer has it blocked, and converts it only to output it
                    _rename(src, made.input[0], blocked)
                else:
                    src.node.append(helper.make_node("ReorderInput", [name], [blocked], domain=NCHWC_DOMAIN,
                                                     channels_last=0))
                src.output.append(helper.make_tensor_value_info(blocked, TensorProto.FLOAT, None))
            _read_instead(graph, readers, name, blocked, TensorProto.FLOAT)
            handed.append(name)
    for name in handed:   # its plain form, where no graph reads it any more, stays inside its producer
        if not any(i.name == name for m in models for i in m.graph.input):
            src = models[producer[name]].graph
            kept = [o for o in src.output if o.name != name]
            del src.output[:]
            src.output.extend(kept)
            unread = [n for n in src.node if n.op_type == "ReorderOutput" and list(n.output) == [name]
                      and not any(name in m.input for m in src.node)]
            for n in unread:   # the conversion that made it
                src.node.remove(n)
    return handed


#: the suffix of a tensor handed over channels-last (``hand_off_channels_last``)
NHWC_SUFFIX = ".nhwc"
_TO_NCHW, _TO_NHWC = [0, 3, 1, 2], [0, 2, 3, 1]


def _perm(node) -> "list[int] | None":
    from onnx import helper
    if node.op_type != "Transpose" or node.domain not in ("", "ai.onnx"):
        return None
    return next((list(helper.get_attribute_value(a)) for a in node.attribute if a.name == "perm"), None)


def _channels_last(src, graph, name: str, nhwc: str, elem_type: int) -> bool:
    """Hands ``name`` (an output of graph ``src`` that ``graph`` reads) over channels-last as ``nhwc``
    where every node of ``graph`` that reads it transposes it channels-last and ``src`` made it by
    transposing a channels-last tensor or transposes it so itself (for its exit head); whether it did."""
    from onnx import helper
    back = [n for n in graph.node if name in n.input]
    made = next((n for n in src.node if list(n.output) == [name]), None)
    own = next((n for n in src.node if _perm(n) == _TO_NHWC and list(n.input) == [name]), None)
    from_nhwc = made is not None and _perm(made) == _TO_NCHW
    if not (from_nhwc or own) or not back or not all(_perm(n) == _TO_NHWC for n in back):
        return False
    if not any(o.name == nhwc for o in src.output):
        if from_nhwc:
            _rename(src, made.input[0], nhwc)
        else:
            _rename_input(src, own.output[0], nhwc)
            own.output[0] = nhwc
        src.output.append(helper.make_tensor_value_info(nhwc, elem_type, None))
    _read_instead(graph, back, name, nhwc, elem_type)
    return True


def _drop_unread(src, models: list, name: str) -> None:
    """Takes output ``name`` out of graph ``src`` where no graph of ``models`` reads it any more, and the
    node that made it where nothing else reads that."""
    if any(i.name == name for m in models for i in m.graph.input) or not any(o.name == name for o in src.output):
        return
    kept = [o for o in src.output if o.name != name]
    del src.output[:]
    src.output.extend(kept)
    if not any(name in n.input for n in src.node):
        for node in [n for n in src.node if list(n.output) == [name]]:
            src.node.remove(node)


def hand_off_channels_last(models: list, inputs: list[list[str]], outputs: list[list[str]]) -> list[str]:
    """Rewrites ``models`` (optimised stage graphs in run order) in place so that a tensor one graph makes
    channels-last and the next transposes channels-last again passes channels-last (``NAME.nhwc``):
    onnxruntime runs quantized convolutions so, and the int8 graphs of a calibration bundle hand each
    other uint8 tensors, which the producer transposed channels-first to output them and the reader
    transposes back. The runtime hands them over so between int8 graphs (``explorer.probe.rewrites``); timed
    with both transposes, the host profile predicted the paper design's int8 paths slower than the
    runtime runs them. Returns the names now handed channels-last."""
    producer = {name: i for i, outs in enumerate(outputs) for name in outs}
    handed = []
    for j, model in enumerate(models):
        for name in inputs[j]:
            if name in producer:
                src = models[producer[name]].graph
                elem = next((o.type.tensor_type.elem_type for o in src.output if o.name == name), 1)
                if _channels_last(src, model.graph, name, name + NHWC_SUFFIX, elem):
                    handed.append(name)
    for name in handed:
        _drop_unread(models[producer[name]].graph, models, name)
    return handed


#: the suffixes of a tensor handed over quantized: plain (NCHW) and channels-last
UINT8_SUFFIX, UINT8_NHWC_SUFFIX = ".uint8", ".uint8_nhwc"


def same_constant(a_graph, a: str, b_graph, b: str) -> bool:
    from onnx import numpy_helper
    ta = next((i for i in a_graph.initializer if i.name == a), None)
    tb = next((i for i in b_graph.initializer if i.name == b), None)
    if ta is None or tb is None:
        return False
    x, y = numpy_helper.to_array(ta), numpy_helper.to_array(tb)
    return x.dtype == y.dtype and x.shape == y.shape and bool((x == y).all())


def hand_off_quantized(models: list, inputs: list[list[str]], outputs: list[list[str]]) -> dict[str, str]:
    """Rewrites ``models`` (optimised stage graphs in run order) in place so that int8 stages hand each
    other uint8 tensors; returns ``{name: "uint8" or "uint8 nhwc"}`` for the tensors now handed so.

    An int8 stage dequantizes the tensor it outputs and the int8 stage that reads it quantizes it again
    at once. Where the reader quantizes with the producer's very scale and zero point (an export makes
    them so: ``explorer.deploy.quantize.share_edge_scales``), the pair is the identity and both nodes go: the
    producer outputs its uint8 tensor (``NAME.uint8``). Where, besides, the reader only transposes it
    channels-last (onnxruntime runs quantized convolutions so) and the producer made it by transposing
    its channels-last one, or transposes it so itself (for its exit head), the channels-last tensor is
    handed (``NAME.uint8_nhwc``). A
    conversion that no graph needs any more is dropped from its producer."""
    from onnx import TensorProto, helper   # onnx only where a graph is rewritten: the probe runs without it
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
                       and same_constant(graph, n.input[1], src, dq.input[1])
                       and same_constant(graph, n.input[2], src, dq.input[2]) for n in readers):
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
