"""Stage graphs that hand tensors to the next stage in onnxruntime's blocked channel layout.

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
output it, the blocked tensor is output instead and the conversion dropped. The rewritten graphs hold
this machine's block size and fused kernels, so a runner makes them when it loads and never stores them.
"""

from __future__ import annotations

from onnx import ModelProto, TensorProto, helper

from explorer.cost.probe_script import NCHWC_DOMAIN as NCHWC

SUFFIX = ".nchwc"


def _is_plain_reorder_in(node) -> bool:
    channels_last = next((helper.get_attribute_value(a) for a in node.attribute if a.name == "channels_last"), 0)
    return node.op_type == "ReorderInput" and node.domain == NCHWC and channels_last == 0


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


def hand_off_blocked(models: list[ModelProto], inputs: list[list[str]], outputs: list[list[str]]) -> list[str]:
    """Rewrites ``models`` (optimised stage graphs in run order; ``inputs`` and ``outputs``: the names
    each one reads and writes) in place; returns the names of the tensors now handed over blocked. A
    tensor is, when every node of its reader that reads it converts it to the blocked layout."""
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
                made = next((n for n in src.node if n.op_type == "ReorderOutput" and n.domain == NCHWC
                             and list(n.output) == [name]), None)
                if own is not None:        # the producer converts it already (for its exit head)
                    _rename_input(src, own.output[0], blocked)
                    own.output[0] = blocked
                elif made is not None:     # the producer has it blocked, and converts it only to output it
                    _rename(src, made.input[0], blocked)
                else:
                    src.node.append(helper.make_node("ReorderInput", [name], [blocked], domain=NCHWC,
                                                     channels_last=0))
                src.output.append(helper.make_tensor_value_info(blocked, TensorProto.FLOAT, None))
            for node in readers:
                graph.node.remove(node)
                _rename_input(graph, node.output[0], blocked)
            kept = [i for i in graph.input if i.name != name]
            del graph.input[:]
            graph.input.extend(kept)
            graph.input.append(helper.make_tensor_value_info(blocked, TensorProto.FLOAT, None))
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
