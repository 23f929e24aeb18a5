"""What the decoder's skip additions cost outside onnxruntime's blocked layout: the paper design's
whole graph as onnxruntime optimises it, against the same optimised graph with each skip addition
rewritten to stay blocked. Not used by the package; a measurement for a possible rewrite.

In the optimised graph a skip addition leaves the blocked (NCHWc) layout: the upsampled decoder tensor
and the skip are converted to NCHW, the skip's channels are sliced (or zero-padded) to the decoder's
width, they are added, and the sum is converted back. When both widths are multiples of the block
size, the slice or pad can act on the blocked tensor seen as (N, C / block, H, W, block), and the
addition of two blocked tensors of one shape is an ordinary element-wise Add, so nothing is converted.
The depth maps are compared with the original graph's.

Why it is not in the runtime: the calibration (the probe, which runs on devices with onnxruntime and
numpy only) and held-out measurement time the plain graphs; a runtime faster than what they measure
would leave the host model and the measured anytime curve apart.

    .venv/bin/python benchmarks/bench_blocked_skip.py [--reps 7]
"""

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from explorer.cost.measure import session, time_call
from explorer.model import build_network
from explorer.onnx_stages import example_inputs, export_whole
from explorer.space import paper_candidate


def block_size() -> int:
    """onnxruntime's channel block on this machine: what 4 channels are padded to."""
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, 1, 1])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
    node = helper.make_node("ReorderInput", ["x"], ["y"], domain="com.microsoft.nchwc", channels_last=0)
    model = helper.make_model(helper.make_graph([node], "block", [x], [y]),
                              opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft.nchwc", 1)])
    return session(model.SerializeToString(), optimize=False).run(None, {"x": np.zeros((1, 4, 1, 1), np.float32)})[0].shape[1]


def blocked_skip_adds(model: onnx.ModelProto, block: int) -> int:
    """Rewrites in place each Add(ReorderOutput(u), Slice|Pad(ReorderOutput(s))) -> ReorderInput into
    an Add of blocked tensors; returns how many."""
    g = model.graph
    made_by = {o: n for n in g.node for o in n.output}
    reads = lambda name: [n for n in g.node if name in n.input]  # noqa: E731
    channels = lambda n: next(helper.get_attribute_value(a) for a in n.attribute if a.name == "channels")  # noqa: E731
    done = 0
    for add in [n for n in g.node if n.op_type == "Add" and n.domain == "" and len(n.input) == 2]:
        upsampled, fitted = made_by.get(add.input[0]), made_by.get(add.input[1])
        if upsampled is None or fitted is None or upsampled.op_type != "ReorderOutput" \
                or fitted.op_type not in ("Slice", "Pad"):
            continue
        skip = made_by.get(fitted.input[0])
        after = reads(add.output[0])
        if skip is None or skip.op_type != "ReorderOutput" or len(after) != 1 or after[0].op_type != "ReorderInput":
            continue
        cx, cs = channels(upsampled), channels(skip)
        if cx % block or cs % block:
            continue
        tag = add.output[0]
        as5 = numpy_helper.from_array(np.array([0, cs // block, -1, block], np.int64), tag + ".as5")
        g.initializer.append(as5)
        nodes = [helper.make_node("Reshape", [skip.input[0], as5.name], [tag + ".s5"])]
        if fitted.op_type == "Slice":
            for name, value in (("start", 0), ("end", cx // block), ("axis", 1)):
                g.initializer.append(numpy_helper.from_array(np.array([value], np.int64), f"{tag}.{name}"))
            nodes.append(helper.make_node("Slice", [tag + ".s5", tag + ".start", tag + ".end", tag + ".axis"],
                                          [tag + ".fit5"]))
        else:
            pads = numpy_helper.from_array(np.array([0, 0, 0, 0, 0, cx // block - cs // block, 0, 0], np.int64),
                                           tag + ".pads")
            g.initializer.append(pads)
            nodes.append(helper.make_node("Pad", [tag + ".s5", pads.name], [tag + ".fit5"]))
        nodes += [helper.make_node("Shape", [upsampled.input[0]], [tag + ".shape"]),
                  helper.make_node("Reshape", [tag + ".fit5", tag + ".shape"], [tag + ".fit"]),
                  helper.make_node("Add", [upsampled.input[0], tag + ".fit"], [after[0].output[0]])]
        at = list(g.node).index(add)
        for n in (after[0], add, fitted, upsampled):
            g.node.remove(n)
        if not reads(skip.output[0]) and skip.output[0] not in {o.name for o in g.output}:
            g.node.remove(skip)
        for k, n in enumerate(nodes):
            g.node.insert(at + k, n)
        done += 1
    return done


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args()
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    whole = export_whole(net, (224, 224))
    feeds = {k: v.numpy() for k, v in example_inputs((224, 224)).items()}
    with tempfile.TemporaryDirectory() as tmp:
        plain = session(whole, save_optimized=Path(tmp) / "optimised.onnx")
        model = onnx.load(str(Path(tmp) / "optimised.onnx"))
    block = block_size()
    count = blocked_skip_adds(model, block)
    blocked = session(model.SerializeToString(), optimize=False)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(plain.run(None, feeds), blocked.run(None, feeds)))
    print(f"block size {block}; {count} skip additions rewritten; max |difference| of the depth maps {diff:.2e}")
    times: dict[str, list[float]] = {"as optimised": [], "blocked skip additions": []}
    for rep in range(args.reps):   # interleaved
        times["as optimised"].append(time_call(lambda: plain.run(None, feeds), 3, 40))
        times["blocked skip additions"].append(time_call(lambda: blocked.run(None, feeds), 3, 40))
        print(f"  rep {rep + 1}: " + ", ".join(f"{k} {v[-1]:.2f} ms" for k, v in times.items()))
    a, b = (statistics.median(v) for v in times.values())
    ratios = [x / y for x, y in zip(*times.values())]
    print(f"paper design whole graph at 224x224, medians of {args.reps}: as optimised {a:.2f} ms, blocked skip "
          f"additions {b:.2f} ms: {statistics.median(ratios):.3f}x per rep ({min(ratios):.3f}-{max(ratios):.3f})")
