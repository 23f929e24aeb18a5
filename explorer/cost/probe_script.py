"""The device probe: times a calibration bundle's ONNX graphs and samples the power sensors Linux
exposes, with nothing but Python 3, numpy and onnxruntime.

This file is copied verbatim into every bundle as ``probe.py`` (``explorer calibrate --bundle``), so
it imports nothing from the package; ``explorer calibrate`` runs the same functions in-process, so a
profile fitted from a probe run and one calibrated directly share one measurement path.

    tar xf probe.tar && python probe.py --out results.json     # on the device
    explorer calibrate --fit results.json --out myboard.yaml   # anywhere

Results are written atomically after every graph: an interrupted probe, run again with the same
``--out``, keeps what it had measured and measures only the rest. Two fixed graphs (a convolution,
a stage) are re-timed every ``SPEED_CHECK_EVERY`` graphs; graphs timed while either shows the machine
running slow (another load, throttling) are timed again, the faster timing is kept, and the change
of speed is kept in the results.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Sequence

try:
    import numpy as np
except ImportError:  # main() says what to install, in one line
    np = None

BUNDLE_FORMAT = "explorer-probe-bundle"
RESULTS_FORMAT = "explorer-probe-results"
VERSION = 1                       # of both the bundle layout and the results file
DEFAULT_PROVIDER = "CPUExecutionProvider"
WARMUP = 3


class ProbeError(Exception):
    """A mistake the user can fix: printed as one line, exit status 2."""


# -- sessions and timing -------------------------------------------------------------------------
def default_threads() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def check_provider(provider: str) -> None:
    import onnxruntime as ort
    have = ort.get_available_providers()
    if provider not in have:
        raise ProbeError(f"execution provider {provider} is not in this onnxruntime {ort.__version__} "
                         f"(it has {', '.join(have)}); install the onnxruntime build that has it, or pick one of those")


#: Environment variable: "session" gives every session its own thread pool instead of the shared one
#: (for programs that also create onnxruntime sessions of their own, which a global pool forbids).
POOL_ENV = "EXPLORER_ORT_POOL"
_POOL: dict[str, "int | bool | None"] = {}   # "threads" of the shared pool; "arena": one shared arena


def shared_pool_threads() -> "int | None":
    """Threads of onnxruntime's global intra-op pool when this process's sessions share it, else None."""
    return _POOL.get("threads")


def shared_arena() -> bool:
    """Whether this process's sessions allocate from one shared memory arena (``_shared_arena``)."""
    return bool(_POOL.get("arena"))


def thread_pool() -> str:
    """What measurement conditions record: 'shared' or 'per-session'."""
    return "shared" if shared_pool_threads() else "per-session"


def _shared_pool(threads: int) -> bool:
    """Every session of this process shares onnxruntime's one global intra-op pool, created by the
    first session. Stages run one after another, so one pool serves them all, and its threads spin
    between operators. Pools of their own either sleep between operators (waking them took 1.5x as
    long in some sessions as in others on this project's 2-core VM: bimodal timings) or, spinning,
    fight each other for the cores (4x slower with a dozen stage sessions alive)."""
    if "threads" not in _POOL:
        _POOL["threads"] = None
        if os.environ.get(POOL_ENV, "shared") != "session":
            import onnxruntime as ort
            try:
                ort.set_global_thread_pool_sizes(threads, 1)
                _POOL["threads"] = threads
            except AttributeError:   # an onnxruntime without global pools: per-session ones
                pass
            except Exception:   # someone in this process made the global pools already: share them
                _POOL["threads"] = threads
            if _POOL["threads"] is not None:
                _POOL["arena"] = _shared_arena(ort)
    return _POOL["threads"] is not None


def _shared_arena(ort) -> bool:
    """Registers one CPU memory arena for every session of the process to allocate from. On this
    project's Zen 4 VM, calm, the paper design's stage sessions ran 5.9-8.0% slower than its whole
    graph with arenas of their own, and 1.1-2.5% faster with one shared arena: buffers are reused
    from stage to stage instead of each stage keeping its own apart (benchmarks/bench_runtime.py).
    While that VM was slowed from outside (whole graph 14 ms, not 7.6), it went the other way:
    -9.0% with their own, +4.9% shared; so the runtime keeps both (``explorer._arena_choice``)."""
    try:
        info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
        ort.create_and_register_allocator(info, ort.OrtArenaCfg(0, -1, -1, -1))
        return True
    except AttributeError:   # an onnxruntime without shared allocators
        return False
    except Exception:   # registered already in this process: share it
        return True


def session(model: "bytes | str | Path", threads: int | None = None, provider: str = DEFAULT_PROVIDER,
            optimize: bool = True, save_optimized: "Path | None" = None, own_arena: bool = False,
            blocked_skips: bool = True):
    """An onnxruntime session as every measurement and the runtime use it: ``threads`` intra-op
    threads (the process's shared pool has those of its first session) and, with that pool, the
    process's one memory arena (``_shared_arena``; ``own_arena``: one of its own instead), full graph
    optimisation (none for a graph optimised already; ``save_optimized``: where to write the optimised
    graph), then, on the CPU provider, the decoder's skip additions kept in the blocked layout
    (``blocked_skip_adds``; ``blocked_skips=False``: as onnxruntime left them), ``provider`` first
    (the CPU one takes what it cannot run)."""
    if optimize and blocked_skips and provider == DEFAULT_PROVIDER and _onnx() is not None:
        import tempfile
        with tempfile.TemporaryDirectory() as tmp:
            optimized = Path(tmp) / "optimized.onnx"
            sess = _session(model, threads, provider, True, optimized, own_arena)
            graph = _onnx().load(str(optimized))
            if not blocked_skip_adds(graph) + channels_last_skip_adds(graph):
                if save_optimized is not None:
                    shutil.copyfile(optimized, save_optimized)
                return sess
        rewritten = graph.SerializeToString()
        if save_optimized is not None:
            Path(save_optimized).write_bytes(rewritten)
        return _session(rewritten, threads, provider, False, None, own_arena)
    return _session(model, threads, provider, optimize, save_optimized, own_arena)


def _session(model, threads, provider, optimize, save_optimized, own_arena):
    import onnxruntime as ort
    opts = ort.SessionOptions()
    threads = threads or default_threads()
    if _shared_pool(threads):
        opts.use_per_session_threads = False
        if _POOL.get("arena") and not own_arena:
            opts.add_session_config_entry("session.use_env_allocators", "1")
    else:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        # Stages run one after another in separate sessions: threads spinning after one stage would
        # steal the cores from the next.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize
                                     else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    if save_optimized is not None:
        opts.optimized_model_filepath = str(save_optimized)
    opts.log_severity_level = 3
    providers = [provider] + ([DEFAULT_PROVIDER] if provider != DEFAULT_PROVIDER else [])
    return ort.InferenceSession(str(model) if isinstance(model, Path) else model, opts, providers=providers)


# -- the decoder's skip additions in the blocked layout ----------------------------------------
NCHWC_DOMAIN = "com.microsoft.nchwc"


def _onnx():
    """The onnx package, where this Python has it (the rewrite below needs it; the probe does not)."""
    try:
        import onnx
    except ImportError:
        return None
    return onnx


def block_size() -> int:
    """onnxruntime's channel block on this machine (8 with AVX2, 16 with AVX-512): what 4 channels
    are padded to by its ReorderInput."""
    if "block" not in _POOL:
        from onnx import TensorProto, helper
        x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 1, 1])
        y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
        node = helper.make_node("ReorderInput", ["x"], ["y"], domain=NCHWC_DOMAIN, channels_last=0)
        model = helper.make_model(helper.make_graph([node], "block", [x], [y]),
                                  opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(NCHWC_DOMAIN, 1)])
        sess = _session(model.SerializeToString(), None, DEFAULT_PROVIDER, False, None, False)
        _POOL["block"] = int(sess.run(None, {"x": np.zeros((1, 4, 1, 1), np.float32)})[0].shape[1])
    return int(_POOL["block"])


def blocked_skip_adds(model, block: "int | None" = None) -> int:
    """Rewrites, in place, onnxruntime's optimised graph ``model`` so that each of the decoder's skip
    additions stays in the blocked (NCHWc) layout; returns how many it rewrote.

    onnxruntime leaves the blocked layout around a skip addition: it converts the up-sampled decoder
    tensor and the skip to NCHW, slices (or zero-pads) the skip's channels to the decoder's width, adds,
    and converts the sum back. Where both widths are multiples of the block, the slice or pad acts on
    the blocked skip seen as (N, C / block, H x W, block), and two blocked tensors of one shape add
    element-wise, so none of the three conversions is needed (a skip that is a graph input, in a stage
    graph, is converted once, and the runtime then hands it over blocked). The paper design's whole
    graph at 224x224: 1.09x faster on an AVX-512 VM, 1.06x on an AVX2 one
    (benchmarks/bench_blocked_skip.py); the results are identical."""
    from onnx import TensorProto, helper, numpy_helper
    g = model.graph
    made_by = {o: n for n in g.node for o in n.output}
    consts = {i.name: i for i in g.initializer}
    inputs = {i.name: i for i in g.input}
    readers = lambda name: [n for n in g.node if name in n.input]  # noqa: E731

    def ints(name: str) -> "list[int] | None":
        return [int(v) for v in numpy_helper.to_array(consts[name]).reshape(-1)] if name in consts else None

    def channels(name: str) -> "int | None":
        node = made_by.get(name)
        if node is not None and node.op_type == "ReorderOutput" and node.domain == NCHWC_DOMAIN:
            return next((helper.get_attribute_value(a) for a in node.attribute if a.name == "channels"), None)
        dims = inputs[name].type.tensor_type.shape.dim if name in inputs else []
        return dims[1].dim_value or None if len(dims) == 4 else None

    def fits_channels_only(fit, cs: int, cx: int) -> bool:
        """Whether ``fit`` only takes the skip's first ``cx`` channels, or pads it with zero channels."""
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

    done, b = 0, block
    for add in [n for n in g.node if n.op_type == "Add" and n.domain == "" and len(n.input) == 2]:
        for up_name, fit_name in (add.input, reversed(add.input)):
            up, fit = made_by.get(up_name), made_by.get(fit_name)
            if up is not None and up.op_type == "ReorderOutput" and fit is not None and fit.op_type in ("Slice", "Pad"):
                break
        else:
            continue
        after = readers(add.output[0])
        is_output = add.output[0] in {o.name for o in g.output}   # a stage graph's, for the next stage
        skip = fit.input[0]
        cx, cs = channels(up_name), channels(skip)
        if (len(after) > 1 or not (after or is_output) or any(n.op_type != "ReorderInput" for n in after)
                or not cx or not cs or len(readers(fit.output[0])) != 1 or not fits_channels_only(fit, cs, cx)):
            continue
        b = b or block_size()
        if cx % b or cs % b:
            continue
        tag = add.output[0]
        skip_node = made_by.get(skip)
        nodes = []
        if skip_node is not None and skip_node.op_type == "ReorderOutput":
            blocked_skip = skip_node.input[0]
        else:   # a graph input: converted here, once
            blocked_skip = tag + ".skip"
            nodes.append(helper.make_node("ReorderInput", [skip], [blocked_skip], domain=NCHWC_DOMAIN,
                                          channels_last=0))
        g.initializer.append(numpy_helper.from_array(np.array([0, cs // b, -1, b], np.int64), tag + ".as5"))
        nodes.append(helper.make_node("Reshape", [blocked_skip, tag + ".as5"], [tag + ".s5"]))
        if fit.op_type == "Slice":
            for name, value in (("start", 0), ("end", cx // b), ("axis", 1)):
                g.initializer.append(numpy_helper.from_array(np.array([value], np.int64), f"{tag}.{name}"))
            nodes.append(helper.make_node("Slice", [tag + ".s5", tag + ".start", tag + ".end", tag + ".axis"],
                                          [tag + ".fit5"]))
        else:
            g.initializer.append(numpy_helper.from_array(
                np.array([0, 0, 0, 0, 0, (cx - cs) // b, 0, 0], np.int64), tag + ".pads"))
            nodes.append(helper.make_node("Pad", [tag + ".s5", tag + ".pads"], [tag + ".fit5"]))
        summed = after[0].output[0] if after else tag + ".blocked"
        nodes += [helper.make_node("Shape", [up.input[0]], [tag + ".shape"]),
                  helper.make_node("Reshape", [tag + ".fit5", tag + ".shape"], [tag + ".fit"]),
                  helper.make_node("Add", [up.input[0], tag + ".fit"], [summed])]
        if is_output:
            nodes.append(helper.make_node("ReorderOutput", [summed], [add.output[0]], domain=NCHWC_DOMAIN,
                                          channels_last=0, channels=cx))
        for n in after + [add, fit]:
            g.node.remove(n)
        outputs = {o.name for o in g.output}
        for n in (up, skip_node):   # conversions nothing reads any more
            if n is not None and n.op_type == "ReorderOutput" and not readers(n.output[0]) \
                    and n.output[0] not in outputs:
                g.node.remove(n)
        at = next((k for k, n in enumerate(g.node) if summed in n.input or add.output[0] in n.input),
                  len(g.node))   # before its readers
        for k, n in enumerate(nodes):
            g.node.insert(at + k, n)
        made_by = {o: n for n in g.node for o in n.output}
        done += 1
    if done:
        del g.value_info[:]   # shapes onnxruntime inferred for tensors that are gone or now blocked
    return done


def channels_last_skip_adds(model) -> int:
    """Rewrites, in place, onnxruntime's optimised graph ``model`` so that each quantized skip addition
    (QLinearAdd) whose decoder side is transposed channels-first only for it adds channels-last; returns
    how many it rewrote.

    onnxruntime runs quantized convolutions channels-last, but leaves a QLinearAdd channels-first: the
    up-sampled decoder tensor is transposed channels-first for the addition and the sum back for the
    next convolution (on the paper design's 768-channel decoder 1, 0.12-0.15 ms each, a quarter of the
    int8 stage). An addition is element-wise, so the skip is transposed channels-last instead (before
    its slice or zero pad to the decoder's width, which then act on the last axis), and the sum stays
    channels-last for the readers that transposed it so; the others get it transposed back. A skip that
    is a graph input is transposed where it enters, which the runtime's handoff removes where its
    producer made it channels-last (``hand_off_channels_last``). The results are identical."""
    from onnx import helper, numpy_helper
    g = model.graph
    made_by = {o: n for n in g.node for o in n.output}
    consts = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    four_d = {i.name for i in g.input if len(i.type.tensor_type.shape.dim) == 4}
    outputs = {o.name for o in g.output}
    readers = lambda name: [n for n in g.node if name in n.input]  # noqa: E731
    to_last = lambda axes: [_TO_NHWC.index(int(a) % 4) for a in axes]  # noqa: E731

    def add_const(name: str, value: list[int]) -> str:
        g.initializer.append(numpy_helper.from_array(np.array(value, np.int64), name))
        return name

    done = 0
    for add in [n for n in g.node if n.op_type == "QLinearAdd" and n.domain == "com.microsoft"]:
        for a, b in ((0, 3), (3, 0)):
            up = made_by.get(add.input[a])
            if up is not None and _perm(up) == _TO_NCHW:
                break
        else:
            continue
        fit = made_by.get(add.input[b])
        fit = fit if fit is not None and fit.op_type in ("Slice", "Pad") and fit.domain in ("", "ai.onnx") else None
        skip = fit.input[0] if fit is not None else add.input[b]
        made = made_by.get(skip)
        quantized_input = made is not None and made.op_type == "QuantizeLinear" and made.input[0] in four_d
        if not (skip in four_d or quantized_input or (made is not None and _perm(made) == _TO_NCHW)):
            continue   # a skip of unknown rank: transposing it might break the broadcast
        tag = add.output[0]
        if fit is not None:
            if len(readers(fit.output[0])) != 1 or fit.output[0] in outputs \
                    or any(n and n not in consts for n in fit.input[1:]):
                continue
            if fit.op_type == "Slice":
                axes = consts[fit.input[3]] if len(fit.input) > 3 and fit.input[3] else range(len(consts[fit.input[1]]))
                new_inputs = list(fit.input[:3]) + [add_const(tag + ".fit_axes", to_last(axes))] + list(fit.input[4:])
            elif len(fit.input) > 3 and fit.input[3]:
                new_inputs = list(fit.input[:3]) + [add_const(tag + ".fit_axes", to_last(consts[fit.input[3]]))]
            else:
                pads = [int(v) for v in consts[fit.input[1]].reshape(-1)]
                if len(pads) != 8:
                    continue
                new_inputs = [fit.input[0], add_const(tag + ".fit_pads", [pads[p] for p in _TO_NHWC]
                                                      + [pads[4 + p] for p in _TO_NHWC])] + list(fit.input[2:])
            del fit.input[:]
            fit.input.extend(new_inputs)
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
        after = readers(tag)
        for n in [n for n in after if _perm(n) == _TO_NHWC and n.output[0] not in outputs]:
            g.node.remove(n)
            _rename_input(g, n.output[0], summed)
        if readers(tag) or tag in outputs:
            g.node.insert(list(g.node).index(add) + 1,
                          helper.make_node("Transpose", [summed], [tag], perm=_TO_NCHW, name=tag + ".nchw"))
        if not readers(up.output[0]) and up.output[0] not in outputs:
            g.node.remove(up)
        made_by = {o: n for n in g.node for o in n.output}
        done += 1
    if done:
        del g.value_info[:]   # shapes onnxruntime inferred for tensors now channels-last
    return done


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
    transposes back. The runtime hands them over so between int8 graphs (``explorer._layout``); timed
    with both transposes, the host profile predicted the paper design's int8 paths 4-10% slower than
    the runtime ran them on a Zen 4 VM. Returns the names now handed channels-last."""
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


def chain_sessions(models: Sequence["bytes | Path"], threads: "int | None" = None,
                   provider: str = DEFAULT_PROVIDER) -> list:
    """Sessions (``session``) for graphs that run one after another and feed each other by tensor name,
    as the runtime runs a model's stage graphs: on the CPU provider, where this Python has ``onnx``, a
    tensor that one graph outputs and the next converts into the blocked layout is handed over blocked
    (``hand_off_blocked``; its name then ends in ``SUFFIX``), and one that it makes channels-last and the
    next transposes channels-last again, channels-last (``hand_off_channels_last``). What the probe and
    the held-out timings time a candidate's stage graphs with: timed alone, each stage paid the layout
    conversions at its edges that the runtime does not, and the host profile predicted the paper
    design's paths 5-14% slow on an AVX-512 VM (benchmarks/bench_runtime.py)."""
    import tempfile
    if provider != DEFAULT_PROVIDER or _onnx() is None:
        return [session(m, threads, provider) for m in models]
    with tempfile.TemporaryDirectory() as tmp:
        sessions = [session(m, threads, provider, save_optimized=Path(tmp) / f"{k}.onnx") for k, m in enumerate(models)]
        try:
            graphs = [_onnx().load(str(Path(tmp) / f"{k}.onnx")) for k in range(len(models))]
            ins = [[i.name for i in s.get_inputs()] for s in sessions]
            outs = [[o.name for o in s.get_outputs()] for s in sessions]
            handed = hand_off_blocked(graphs, ins, outs) + hand_off_channels_last(graphs, ins, outs)
        except Exception:   # an onnxruntime whose optimised graphs the rewrite does not know
            return sessions
    if not handed:
        return sessions
    return [session(g.SerializeToString(), threads, provider, optimize=False) for g in graphs]


def time_call(fn: Callable[[], object], warmup: int = WARMUP, repeats: int = 15) -> float:
    """Median wall time of ``fn`` in ms after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(samples)


def time_chain(fns: Sequence[Callable[[], object]], warmup: int = WARMUP, repeats: int = 15,
               timed: "Sequence[bool] | None" = None,
               new_round: "Callable[[], object] | None" = None) -> "list[float | None]":
    """Median wall time in ms of each of ``fns`` (those ``timed``; None for the others), called in order
    ``warmup`` rounds untimed, then ``repeats`` rounds timed, ``new_round`` (untimed) before each: a
    model's stage graphs as the runtime runs them, one after another, each reading what the one before
    it wrote. Timed each on its own, over and over, the paper design's 12 stage graphs
    took 4-7% less in all than in sequence (the small ones, exit heads and the fusion unit, 13-60% less)
    on an AVX-512 VM, and the host profile predicted the runtime's paths 4-7% fast."""
    timed = list(timed) if timed is not None else [True] * len(fns)
    for _ in range(warmup):
        if new_round is not None:
            new_round()
        for fn in fns:
            fn()
    samples: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        if new_round is not None:
            new_round()
        for fn, kept in zip(fns, samples):
            t0 = time.perf_counter()
            fn()
            kept.append((time.perf_counter() - t0) * 1000.0)
    return [statistics.median(t) if on else None for t, on in zip(samples, timed)]


def chain_runs(chain: list, start: dict) -> "tuple[list[Callable[[], object]], Callable[[], object]]":
    """One call per session of ``chain``, each reading its inputs from what ``start`` and the sessions
    before it hold, and the call that starts a new round from ``start``."""
    env = dict(start)

    def run(sess, ins, outs) -> None:
        env.update(zip(outs, sess.run(outs, {n: env[n] for n in ins})))

    def new_round() -> None:
        env.clear()
        env.update(start)
    return ([lambda s=s, i=[x.name for x in s.get_inputs()], o=[x.name for x in s.get_outputs()]: run(s, i, o)
             for s in chain], new_round)


# -- power sensors -------------------------------------------------------------------------------
def _read_number(path: str) -> float:
    with open(path) as f:
        return float(f.read().strip())


def _read_text(path: str, default: str = "") -> str:
    try:
        with open(path) as f:
            return f.read().strip().strip("\x00")
    except OSError:
        return default


def _is_input_rail(label: str) -> bool:
    """The board's input rail (VDD_IN on TX2/Orin, POM_5V_IN on Nano) already includes every other
    rail: summing it with them would count the SoC twice."""
    up = label.upper()
    return up == "IN" or up.endswith("_IN")


def _pick_rails(rails: list[tuple[str, object]]) -> list[tuple[str, object]]:
    inputs = [r for r in rails if _is_input_rail(r[0])]
    return inputs or rails


class PowerSensor:
    """A readable power source. ``kind`` 'power': ``read()`` is watts now; 'energy': ``read()`` is a
    counter and ``joules(a, b)`` the energy between two readings."""

    kind = "power"
    name = "sensor"
    what = ""
    interval_s = 0.02   # between samples while sampling in the background

    def read(self):  # pragma: no cover - interface
        raise NotImplementedError

    def joules(self, a, b) -> float:  # pragma: no cover - energy counters only
        raise NotImplementedError

    def describe(self) -> dict:
        return {"sensor": self.name, "kind": self.kind, "what": self.what}


class Ina3221Hwmon(PowerSensor):
    """Jetson INA3221 through hwmon: ``in{N}_input`` bus millivolts, ``curr{N}_input`` milliamperes."""

    name = "ina3221-hwmon"

    def __init__(self, channels: list[tuple[str, tuple[str, str]]]) -> None:
        self.channels = channels
        self.what = "rails " + ", ".join(label for label, _ in channels)

    def read(self) -> float:
        return sum(_read_number(v) * _read_number(c) for _, (v, c) in self.channels) / 1e6

    @classmethod
    def find(cls, root: str) -> "Ina3221Hwmon | None":
        rails = []
        for dev in sorted(glob.glob(os.path.join(root, "sys/class/hwmon/hwmon*"))):
            if _read_text(os.path.join(dev, "name")) != "ina3221":
                continue
            for volt in sorted(glob.glob(os.path.join(dev, "in[0-9]*_input"))):
                n = re.fullmatch(r"in(\d+)_input", os.path.basename(volt)).group(1)
                curr = os.path.join(dev, f"curr{n}_input")
                if os.path.isfile(curr) and _readable(volt) and _readable(curr):
                    label = _read_text(os.path.join(dev, f"in{n}_label"), f"{os.path.basename(dev)}/in{n}")
                    rails.append((label, (volt, curr)))
        return cls(_pick_rails(rails)) if rails else None


class Ina3221Iio(PowerSensor):
    """Older Jetson kernels (TX1/TX2, L4T 28-32): the ina3221x iio driver's ``in_power{N}_input``
    in milliwatts, rail names in ``rail_name_{N}``."""

    name = "ina3221-iio"

    def __init__(self, channels: list[tuple[str, str]]) -> None:
        self.channels = channels
        self.what = "rails " + ", ".join(label for label, _ in channels)

    def read(self) -> float:
        return sum(_read_number(p) for _, p in self.channels) / 1e3

    @classmethod
    def find(cls, root: str) -> "Ina3221Iio | None":
        rails, seen = [], set()
        patterns = ("sys/bus/i2c/drivers/ina3221x/*/iio:device*", "sys/bus/iio/devices/iio:device*")
        for dev in sorted(d for pat in patterns for d in glob.glob(os.path.join(root, pat))):
            real = os.path.realpath(dev)
            if real in seen:
                continue
            seen.add(real)
            for p in sorted(glob.glob(os.path.join(dev, "in_power[0-9]*_input"))):
                n = re.fullmatch(r"in_power(\d+)_input", os.path.basename(p)).group(1)
                if _readable(p):
                    rails.append((_read_text(os.path.join(dev, f"rail_name_{n}"), f"power{n}"), p))
        return cls(_pick_rails(rails)) if rails else None


class HwmonPower(PowerSensor):
    """Any other hwmon device with ``power{N}_input`` (microwatts), summed."""

    name = "hwmon-power"

    def __init__(self, files: list[tuple[str, str]]) -> None:
        self.files = files
        self.what = ", ".join(label for label, _ in files)

    def read(self) -> float:
        return sum(_read_number(p) for _, p in self.files) / 1e6

    @classmethod
    def find(cls, root: str) -> "HwmonPower | None":
        files = []
        for dev in sorted(glob.glob(os.path.join(root, "sys/class/hwmon/hwmon*"))):
            name = _read_text(os.path.join(dev, "name"), os.path.basename(dev))
            if name == "ina3221":
                continue
            for p in sorted(glob.glob(os.path.join(dev, "power[0-9]*_input"))):
                if _readable(p):
                    files.append((f"{name}/{os.path.basename(p)}", p))
        return cls(files) if files else None


class Rapl(PowerSensor):
    """Intel/AMD RAPL through powercap: top-level zones' ``energy_uj`` counters (sub-zones are
    inside them), each wrapping at its ``max_energy_range_uj``."""

    name = "rapl"
    kind = "energy"

    def __init__(self, zones: list[tuple[str, str, float]]) -> None:
        self.zones = zones
        self.what = "zones " + ", ".join(label for label, _, _ in zones)

    def read(self) -> list[float]:
        return [_read_number(p) for _, p, _ in self.zones]

    def joules(self, a: Sequence[float], b: Sequence[float]) -> float:
        total = 0.0
        for (_, _, wrap), x, y in zip(self.zones, a, b):
            d = y - x
            if d < 0:  # the counter wrapped once (a window far shorter than a wrap period)
                d += wrap
            total += d
        return total / 1e6

    @classmethod
    def find(cls, root: str) -> "Rapl | None":
        zones = []
        for z in sorted(glob.glob(os.path.join(root, "sys/class/powercap/*"))):
            base = os.path.basename(z)
            # intel-rapl:0 is a package, intel-rapl:0:0 a part of it; the mmio zone mirrors a package
            if base.count(":") != 1 or "mmio" in base:
                continue
            e, m = os.path.join(z, "energy_uj"), os.path.join(z, "max_energy_range_uj")
            if os.path.isfile(e) and _readable(e):
                wrap = _read_number(m) if os.path.isfile(m) and _readable(m) else 2.0 ** 32
                zones.append((_read_text(os.path.join(z, "name"), base), e, wrap))
        return cls(zones) if zones else None


_PMIC_LINE = re.compile(r"^\s*(\S+)_([AV])\s+(?:current|volt)\(\d+\)=\s*([-+0-9.eE]+)\s*[AV]\s*$")


def parse_pmic_adc(text: str) -> float:
    """Watts from ``vcgencmd pmic_read_adc`` (Raspberry Pi 5): every rail with both a current
    (``NAME_A current(i)=...A``) and a voltage (``NAME_V volt(j)=...V``) line, current x voltage."""
    amps, volts = {}, {}
    for line in text.splitlines():
        m = _PMIC_LINE.match(line)
        if m:
            (amps if m.group(2) == "A" else volts)[m.group(1)] = float(m.group(3))
    rails = set(amps) & set(volts)
    if not rails:
        raise ValueError("no rail with both a current and a voltage")
    return sum(amps[r] * volts[r] for r in rails)


class RpiPmic(PowerSensor):
    """Raspberry Pi 5's PMIC through ``vcgencmd pmic_read_adc`` (each reading starts the command)."""

    name = "rpi5-pmic"
    interval_s = 0.25   # every reading starts a process: sample rarely, so it does not load the CPU

    def __init__(self, command: str) -> None:
        self.command = command
        self.what = f"{command} pmic_read_adc, sum of rail current x voltage"

    def read(self) -> float:
        out = subprocess.run([self.command, "pmic_read_adc"], capture_output=True, text=True, timeout=5,
                             check=True).stdout
        return parse_pmic_adc(out)

    @classmethod
    def find(cls, command: str) -> "RpiPmic | None":
        exe = shutil.which(command)
        if exe is None:
            return None
        sensor = cls(exe)
        try:
            sensor.read()
        except (OSError, ValueError, subprocess.SubprocessError):
            return None
        return sensor


def _readable(path: str) -> bool:
    try:
        _read_number(path)
        return True
    except (OSError, ValueError):
        return False


def find_sensor(root: str = "/", vcgencmd: str = "vcgencmd") -> PowerSensor | None:
    """The first readable power source, board-level ones first (an INA3221 input rail or the Pi's
    PMIC sees the whole board; RAPL sees the CPU package only)."""
    for found in (lambda: Ina3221Hwmon.find(root), lambda: Ina3221Iio.find(root), lambda: RpiPmic.find(vcgencmd),
                  lambda: HwmonPower.find(root), lambda: Rapl.find(root)):
        sensor = found()
        if sensor is not None:
            return sensor
    return None


class PowerWindow:
    """Mean power (W) over a ``with`` block: energy counters read at both ends, instantaneous
    sensors sampled every ``interval_s`` by a background thread (and once at each end)."""

    def __init__(self, sensor: PowerSensor, interval_s: float | None = None) -> None:
        self.sensor, self.interval_s = sensor, interval_s or sensor.interval_s
        self.watts = float("nan")
        self.seconds = 0.0
        self.samples = 0

    def __enter__(self) -> "PowerWindow":
        self._stop = threading.Event()
        self._values: list[float] = []
        if self.sensor.kind == "energy":
            self._start = self.sensor.read()
        else:
            self._values.append(self.sensor.read())
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        self._t0 = time.perf_counter()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._values.append(self.sensor.read())

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self._t0
        if self.sensor.kind == "energy":
            self.watts = self.sensor.joules(self._start, self.sensor.read()) / max(self.seconds, 1e-9)
            self.samples = 2
        else:
            self._stop.set()
            self._thread.join()
            self._values.append(self.sensor.read())
            self.watts = float(np.mean(self._values))
            self.samples = len(self._values)


def idle_power(sensor: PowerSensor, seconds: float) -> float:
    with PowerWindow(sensor) as w:
        time.sleep(seconds)
    return w.watts


def inference_energy(sensor: PowerSensor, run: Callable[[], object], idle_w: float, min_seconds: float,
                     min_runs: int = 3) -> dict:
    """Runs ``run`` back to back for at least ``min_seconds`` while sampling power; the energy of
    one run is (mean power - idle power) x (window / runs)."""
    run()
    n = 0
    with PowerWindow(sensor) as w:
        t0 = time.perf_counter()
        while n < min_runs or time.perf_counter() - t0 < min_seconds:
            run()
            n += 1
    per_run_s = w.seconds / n
    return {"ms": per_run_s * 1000.0, "j": max(w.watts - idle_w, 0.0) * per_run_s, "watts": w.watts,
            "runs": n, "samples": w.samples}


# -- device identity -----------------------------------------------------------------------------
def device_identity(provider: str, threads: int, root: str = "/") -> dict:
    import onnxruntime as ort
    cpuinfo = _read_text(os.path.join(root, "proc/cpuinfo"))
    cpu = ""
    for key in ("model name", "Model", "Hardware", "Processor", "cpu model"):
        m = re.search(rf"^{key}\s*:\s*(.+)$", cpuinfo, re.MULTILINE)
        if m:
            cpu = m.group(1).strip()
            break
    return {"host": platform.node(), "board": _read_text(os.path.join(root, "proc/device-tree/model")),
            "cpu": cpu or platform.processor() or platform.machine(), "machine": platform.machine(),
            "cores": os.cpu_count(), "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version(), "numpy": np.__version__, "onnxruntime": ort.__version__,
            "provider": provider, "threads": threads}


# -- results -------------------------------------------------------------------------------------
def load_manifest(bundle_dir: Path) -> dict:
    path = Path(bundle_dir) / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
    except OSError:
        raise ProbeError(f"{path}: no bundle manifest here (unpack the bundle and run probe.py inside it, "
                         "or pass --bundle DIR)") from None
    except json.JSONDecodeError:
        raise ProbeError(f"{path}: the bundle manifest is not valid JSON (unpack the bundle again)") from None
    if manifest.get("format") != BUNDLE_FORMAT or manifest.get("version") != VERSION:
        raise ProbeError(f"{path}: bundle format {manifest.get('format')} v{manifest.get('version')}, this probe "
                         f"reads {BUNDLE_FORMAT} v{VERSION}: use the probe.py that came in the bundle")
    return manifest


def read_results(path: Path) -> dict:
    """A results file, checked: whole JSON, this format and version."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ProbeError(f"{path}: cannot read results ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise ProbeError(f"{path}: not a whole results file (truncated or corrupt JSON): run the probe again "
                         "with another --out") from None
    if not isinstance(data, dict) or data.get("format") != RESULTS_FORMAT:
        raise ProbeError(f"{path}: not a probe results file (write one with `python probe.py --out FILE`)")
    if data.get("version") != VERSION:
        raise ProbeError(f"{path}: results of probe format v{data.get('version')}, this version reads v{VERSION}: "
                         "make a new bundle with `explorer calibrate --bundle` and probe again")
    for key in ("bundle", "device", "conditions", "layers", "stages"):
        if key not in data:
            raise ProbeError(f"{path}: results file lacks '{key}' (truncated or edited): run the probe again")
    return data


def write_atomically(path: Path, data: dict) -> None:
    """Whole file or the previous one, never half of one: an interrupt loses at most one graph."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _random_feeds(inputs: Iterable[dict], rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {i["name"]: rng.random(tuple(i["shape"]), dtype=np.float32) for i in inputs}


def _candidate_inputs(manifest: dict, rng: np.random.Generator, cand: dict | None = None) -> dict[str, np.ndarray]:
    h, w = (cand or {}).get("input_size") or manifest["input_size"]
    return {"image": rng.random((1, 3, h, w), dtype=np.float32),
            "scan": rng.random((1, w), dtype=np.float32) * 5 + 0.5}


def schedule(layers: list[dict], cands: list[dict]) -> list[tuple[str, dict]]:
    """Layer graphs with the candidates spread evenly among them: a board that heats up and
    throttles (or a machine whose load drifts) then slows both kinds alike, and the fit, which
    reads them together, does not mistake the drift for a difference between them."""
    order: list[tuple[str, dict]] = [("layer", layer) for layer in layers]
    for j, cand in reversed(list(enumerate(cands))):
        order.insert(round((j + 0.5) * len(layers) / len(cands)), ("candidate", cand))
    return order


#: The probe times two fixed graphs first, again after every this many graphs, and last: how much
#: the machine's own speed changed while it measured (another load, throttling), and when.
SPEED_CHECK_EVERY = 12
SPEED_CHECK_REPEATS = 9
#: Graphs timed between two speed checks of which one ran this much slower than the machine's usual
#: speed (``usual_speed``: a shared machine is slowed more often than sped up) are timed again (at
#: most ``REMEASURE_PASSES`` times), once a check shows it back to its usual speed (waiting up to
#: ``CALM_WAIT_S``): a load that came and went leaves no mark.
SLOW = 0.10
REMEASURE_PASSES = 3
CALM_WAIT_S = 60.0
#: A change of speed above this fraction while measuring is reported.
SPEED_DRIFT_WARN = 0.10


def speed_layer(layers: list[dict]) -> "dict | None":
    """The layer graph the probe re-times to follow the machine's speed: the largest float pointwise
    convolution (every thread busy for long enough that a competing load shows)."""
    pointwise = [layer for layer in layers if layer.get("precision", "fp32") == "fp32"
                 and layer["workload"]["kind"] == "pointwise"]
    return max(pointwise, key=lambda layer: layer["workload"]["macs"]) if pointwise else None


def speed_stage(cands: list[dict]) -> "dict | None":
    """The stage graph the probe also re-times: the first candidate's image encoder (about a
    millisecond of mixed operators, which another load slows more than one large convolution:
    measured here, 1.6-2x against 1.2-1.3x)."""
    graphs = cands[0]["graphs"] if cands else []
    return next((g for g in graphs if g["stage"] == "image_encoder"), graphs[0] if graphs else None)


def speed_drift(results: dict) -> "float | None":
    """(slowest / fastest) - 1 of the probe's speed checks (``slowness``), None with fewer than two."""
    ratios = slowness(results.get("speed") or {})
    return max(ratios) / min(ratios) - 1.0 if len(ratios) >= 2 else None


def usual_speed(checks: list[float]) -> float:
    """The time a speed check takes on this machine undisturbed: the 10th percentile of the checks
    (a shared machine was seen slowed for most of a calibration, its first quartile 14% slow)."""
    return float(np.percentile(checks, 10))


def slowness(speed: dict) -> list[float]:
    """Per speed check, how much slower than usual the machine ran (1 = usual; the slower graph's)."""
    series = [speed.get("ms") or []]
    if len(speed.get("stage_ms") or []) == len(series[0]):
        series.append(speed["stage_ms"])
    ratios = [[ms / usual_speed(s) for ms in s] for s in series if s]
    return [max(r) for r in zip(*ratios)]


def wait_until_calm(latest: float, time_again: Callable[[], float], usual: float,
                    wait_s: float = CALM_WAIT_S) -> float:
    """While the fixed graph's ``latest`` time is ``SLOW`` or more above ``usual``, waits a second and
    times it again (``time_again``), for at most ``wait_s``; returns its last time."""
    calm_by = time.monotonic() + wait_s
    while latest > usual * (1 + SLOW) and time.monotonic() < calm_by:
        time.sleep(1.0)   # still slow: give the other load time to finish
        latest = time_again()
    return latest


def fixed_graph_timer(graph: Path, threads: int, provider: str) -> Callable[[], float]:
    """Times one of the speed checks' fixed graphs (``SPEED_CHECK_REPEATS`` runs, median ms), fed as
    the probe feeds it, so that another process can tell how fast the machine runs against a probe's
    checks (``usual_speed`` of its ``speed`` series)."""
    sess = session(graph, threads, provider)
    feeds = _random_feeds(({"name": i.name, "shape": i.shape} for i in sess.get_inputs()), np.random.default_rng(0))
    return lambda: time_call(lambda: sess.run(None, feeds), WARMUP, SPEED_CHECK_REPEATS)


def slow_windows(ratios: list[float]) -> list[int]:
    """Indices j of the windows between check j and check j + 1 (the graphs timed in between) that
    either check shows the machine ``SLOW`` or more slower than usual (``ratios``: ``slowness``)."""
    slow = [x > 1 + SLOW for x in ratios]
    return [j for j in range(len(slow) - 1) if slow[j] or slow[j + 1]]


def set_aside(res: dict, labels: Iterable[str]) -> None:
    """Moves the timings of the graphs ``labels`` (layer ids, or "candidate/stage") from ``res`` to
    its ``earlier`` ones: a probe run on ``res`` times them again and keeps the faster timing."""
    earlier = res.setdefault("earlier", {})
    for label in labels:
        key, _, stage = label.partition("/")
        earlier[label] = res["stages"][key].pop(stage) if stage else res["layers"].pop(key)


def run_probe(bundle_dir: "str | Path", out: "str | Path", provider: str = DEFAULT_PROVIDER,
              threads: int | None = None, repeats: int | None = None, energy: bool = True,
              root: str = "/", vcgencmd: str = "vcgencmd", idle_s: float = 2.0, window_s: float = 1.0,
              progress: Callable[[int, int, str], None] | None = None,
              log: Callable[[str], None] = lambda s: None, remeasure_passes: int = REMEASURE_PASSES,
              calm_wait_s: float = CALM_WAIT_S) -> dict:
    """Times every graph of the bundle (single layers, then each candidate's stages in order, each
    fed by the one before), then, where a power sensor is readable, the energy of whole inferences.
    Returns the results, also written (atomically, after every graph) to ``out``. Graphs timed while a
    speed check showed the machine slow are timed again in up to ``remeasure_passes`` more passes, each
    after waiting up to ``calm_wait_s`` for the machine's usual speed."""
    bundle_dir, out = Path(bundle_dir), Path(out)
    manifest = load_manifest(bundle_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    check_provider(provider)
    threads = threads or default_threads()
    _shared_pool(threads)
    threads = shared_pool_threads() or threads
    repeats = repeats or int(manifest["repeats"])
    cond = {"provider": provider, "threads": threads, "thread_pool": thread_pool(),
            "repeats": repeats, "warmup": WARMUP, "statistic": "median", "stage_graphs": "timed in sequence"}
    if out.exists():
        res = read_results(out)
        if res["bundle"].get("id") != manifest["id"]:
            raise ProbeError(f"{out}: results of another bundle ({res['bundle'].get('id')}, this one is "
                             f"{manifest['id']}): give another --out, or delete it to start over")
        if res["conditions"] != cond:
            raise ProbeError(f"{out}: measured with {res['conditions']}, now asked for {cond}: give another "
                             "--out, or the same options as before to resume")
        log(f"resuming {out}: {len(res['layers'])} layer graphs and "
            f"{sum(len(v) for v in res['stages'].values())} stage graphs already measured")
    else:
        res = {"format": RESULTS_FORMAT, "version": VERSION, "bundle": manifest,
               "device": device_identity(provider, threads, root), "conditions": cond,
               "layers": {}, "stages": {}, "energy": None}
    layers, cands = manifest["layers"], manifest["candidates"]
    total = len(layers) + sum(len(c["graphs"]) for c in cands)
    done = 0

    def tick(what: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, what)

    rng = np.random.default_rng(0)
    reference, reference_stage = speed_layer(layers), speed_stage(cands)
    speed = res.setdefault("speed", {"layer": reference["id"] if reference else None, "ms": [], "remeasured": 0})
    speed.setdefault("stage", reference_stage["file"] if reference and reference_stage else None)
    speed.setdefault("stage_ms", [])
    earlier = res.setdefault("earlier", {})   # timings taken while it ran slow, until timed again
    # each kept timing's speed check before it: judged again after every pass against all checks so
    # far (a machine slowed for a whole pass looks usual until it speeds up)
    timed_after = res.setdefault("timed_after", {})
    since_check = [SPEED_CHECK_EVERY]   # graphs timed since the last speed check
    checks = [(fixed_graph_timer(bundle_dir / file, threads, provider), times)
              for file, times in ((reference and reference["file"], speed["ms"]), (speed["stage"], speed["stage_ms"]))
              if file]

    def check_speed() -> float:
        """Times the fixed graphs (and opens a new window of graphs); returns how much slower than
        usual the machine runs now (1 = usual)."""
        since_check[0] = 0
        if reference is None:
            return 1.0
        for timer, times in checks:
            times.append(timer())
        return slowness(speed)[-1]

    def measure(sess, feeds, label: str) -> float:
        if since_check[0] >= SPEED_CHECK_EVERY:
            check_speed()
        since_check[0] += 1
        timed_after[label] = len(speed["ms"]) - 1
        ms = time_call(lambda: sess.run(None, feeds), WARMUP, repeats)
        return min(ms, earlier.pop(label, ms))

    for attempt in range(remeasure_passes + 1):
        since_check[0] = SPEED_CHECK_EVERY   # each pass opens with a check
        timed_before = dict(timed_after)
        for kind, item in schedule(layers, cands):
            if kind == "layer":
                if item["id"] not in res["layers"]:
                    sess = session(bundle_dir / item["file"], threads, provider)
                    res["layers"][item["id"]] = measure(sess, _random_feeds(item["inputs"], rng), item["id"])
                    write_atomically(out, res)
                tick("layers")
                continue
            kept = res["stages"].setdefault(item["key"], {})
            if all(g["stage"] in kept for g in item["graphs"]):
                for _ in item["graphs"]:
                    tick("stages")
                continue
            start = _candidate_inputs(manifest, rng, item)
            chain = chain_sessions([bundle_dir / g["file"] for g in item["graphs"]], threads, provider)
            runs, new_round = chain_runs(chain, start)
            missing = [g["stage"] not in kept for g in item["graphs"]]
            labels = [f"{item['key']}/{g['stage']}" for g, m in zip(item["graphs"], missing) if m]
            if since_check[0] >= SPEED_CHECK_EVERY:
                check_speed()
            since_check[0] += len(labels)
            for label in labels:
                timed_after[label] = len(speed["ms"]) - 1
            for g, ms in zip(item["graphs"], time_chain(runs, WARMUP, repeats, missing, new_round)):
                if ms is not None:
                    label = f"{item['key']}/{g['stage']}"
                    kept[g["stage"]] = min(ms, earlier.pop(label, ms))
                tick("stages")
            write_atomically(out, res)
        if timed_after == timed_before:
            break   # nothing timed in this pass (a finished run, resumed)
        check_speed()   # closes the last window
        if reference is None or attempt == remeasure_passes:
            break
        slow = set(slow_windows(slowness(speed)))
        again = [label for label, j in timed_after.items() if j in slow]
        if not again:
            break
        log(f"the machine ran slower for a while ({len(again)} graphs timed then): timing those again")
        wait_until_calm(slowness(speed)[-1], check_speed, 1.0, calm_wait_s)
        set_aside(res, again)
        speed["remeasured"] = speed.get("remeasured", 0) + len(again)
        done -= len(layers) + sum(len(c["graphs"]) for c in cands)   # the progress bar goes round again
    write_atomically(out, res)
    drift = speed_drift(res)
    if drift is not None and drift > SPEED_DRIFT_WARN:
        ranges = ", ".join(f"{min(t):.3g}-{max(t):.3g} ms" for t in (speed["ms"], speed["stage_ms"]) if t)
        log(f"note: this machine's speed changed by {drift:.0%} while it was measured (fixed graphs took {ranges}); "
            f"{speed.get('remeasured', 0)} graphs timed while it ran slow were timed again. Another load or "
            "throttling? If the profile disagrees with later measurements, measure again when the machine is idle")
    if energy:
        _probe_energy(res, manifest, bundle_dir, out, provider, threads, root, vcgencmd, idle_s, window_s,
                      progress, log)
    write_atomically(out, res)
    return res


def _probe_energy(res: dict, manifest: dict, bundle_dir: Path, out: Path, provider: str, threads: int,
                  root: str, vcgencmd: str, idle_s: float, window_s: float,
                  progress: Callable[[int, int, str], None] | None, log: Callable[[str], None]) -> None:
    sensor = find_sensor(root, vcgencmd)
    if sensor is None:
        res["energy"] = {"sensor": None, "note": "no readable power sensor (INA3221 hwmon/iio, Raspberry Pi 5 "
                         "PMIC, hwmon power*_input, RAPL energy_uj; RAPL needs root on most kernels): "
                         "energy not measured"}
        log(res["energy"]["note"])
        return
    e = res["energy"] if res.get("energy") and res["energy"].get("sensor") else None
    if e is None:
        log(f"power sensor: {sensor.name} ({sensor.what}); idle power for {idle_s:g} s")
        e = {**sensor.describe(), "idle_w": idle_power(sensor, idle_s), "idle_s": idle_s, "window_s": window_s,
             "inferences": {}}
        res["energy"] = e
        write_atomically(out, res)
    cands = manifest["candidates"]
    rng = np.random.default_rng(1)
    for i, cand in enumerate(cands):
        if cand["key"] not in e["inferences"]:
            sessions = [session(bundle_dir / g["file"], threads, provider) for g in cand["graphs"]]
            io = [([x.name for x in s.get_inputs()], [x.name for x in s.get_outputs()]) for s in sessions]
            start = _candidate_inputs(manifest, rng, cand)

            def inference() -> None:
                env = dict(start)
                for s, (ins, outs) in zip(sessions, io):
                    env.update(zip(outs, s.run(outs, {n: env[n] for n in ins})))

            e["inferences"][cand["key"]] = inference_energy(sensor, inference, e["idle_w"], window_s)
            write_atomically(out, res)
        if progress:
            progress(i + 1, len(cands), "energy")


# -- command line --------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    here = Path(__file__).resolve().parent
    ap = argparse.ArgumentParser(prog="probe.py", description="Time this bundle's ONNX graphs on this device "
                                 "(and sample its power sensors); fit the results anywhere with "
                                 "`explorer calibrate --fit RESULTS --out PROFILE.yaml`.")
    ap.add_argument("--out", required=True, help="results JSON to write (an existing one is resumed)")
    ap.add_argument("--bundle", default=str(here), help="unpacked bundle folder (default: this file's)")
    ap.add_argument("--provider", default=DEFAULT_PROVIDER,
                    help="onnxruntime execution provider (default CPUExecutionProvider; e.g. CUDAExecutionProvider, "
                    "TensorrtExecutionProvider, OpenVINOExecutionProvider, XnnpackExecutionProvider)")
    ap.add_argument("--threads", type=int, default=None, help="intra-op threads (default: all cores)")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per graph (default: the bundle's)")
    ap.add_argument("--no-energy", dest="energy", action="store_false", help="do not sample power sensors")
    ap.add_argument("--idle", type=float, default=2.0, help="seconds of idle power measured first (default 2)")
    ap.add_argument("--window", type=float, default=1.0, help="seconds of back-to-back inferences per "
                    "energy measurement (default 1)")
    ap.add_argument("--sysfs-root", default="/", help="where /sys and /proc are (default /; for tests)")
    ap.add_argument("--vcgencmd", default="vcgencmd", help="the Raspberry Pi's vcgencmd (default: on PATH)")
    args = ap.parse_args(argv)
    try:
        import onnxruntime  # noqa: F401  (checked here: one line, not a traceback, when it is missing)
        if np is None:
            raise ImportError("numpy")
    except ImportError:
        print("probe.py: error: needs onnxruntime and numpy: `python3 -m pip install onnxruntime numpy` "
              "(or your board's onnxruntime build)", file=sys.stderr)
        return 2
    last = [0.0]

    def progress(i: int, n: int, what: str) -> None:
        now = time.monotonic()
        if i == n or now - last[0] > 2.0:
            last[0] = now
            print(f"  {what}: {i}/{n}", file=sys.stderr, flush=True)

    try:
        res = run_probe(args.bundle, args.out, args.provider, args.threads, args.repeats, args.energy,
                        args.sysfs_root, args.vcgencmd, args.idle, args.window, progress,
                        log=lambda s: print(s, file=sys.stderr, flush=True))
    except ProbeError as exc:
        print(f"probe.py: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"probe.py: interrupted; what was measured is in {args.out}: run the same command to go on",
              file=sys.stderr)
        return 130
    d = res["device"]
    print(f"wrote {args.out}: {len(res['layers'])} layer graphs, "
          f"{sum(len(v) for v in res['stages'].values())} stage graphs on {d['cpu']} ({d['provider']}, "
          f"{d['threads']} threads); fit it with `explorer calibrate --fit {args.out} --out myboard.yaml`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
