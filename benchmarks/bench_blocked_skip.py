"""What keeping the decoder's skip additions in onnxruntime's blocked layout saves: the paper
design's whole graph as every session of the package makes it (``session``, which rewrites the skip
additions: ``explorer.probe.blocked_skip_adds``) against the same graph as onnxruntime
optimises it (``blocked_skips=False``), interleaved; then the staged runtime, whose stages also hand
their skips over blocked, against one built with neither. The depth maps are compared.

    .venv/bin/python benchmarks/bench_blocked_skip.py [--reps 7]
"""

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch

import explorer.probe as probe
from explorer.calibration.measure import session, time_call
from explorer.deploy.export import export_network
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.deploy.runtime import AnytimeRunner
from explorer.space import paper_candidate


def report(times: dict[str, list[float]], what: str) -> None:
    (la, a), (lb, b) = times.items()
    ratios = [x / y for x, y in zip(a, b)]
    print(f"{what}, medians of {len(a)}: {la} {statistics.median(a):.2f} ms, {lb} {statistics.median(b):.2f} ms: "
          f"{statistics.median(ratios):.3f}x per rep ({min(ratios):.3f}-{max(ratios):.3f})")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args()
    size = (224, 224)
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    whole = export_whole(net, size)
    feeds = {k: v.numpy() for k, v in example_inputs(size).items()}
    with tempfile.TemporaryDirectory() as tmp:
        plain = session(whole, blocked_skips=False)
        blocked = session(whole, save_optimized=Path(tmp) / "blocked.onnx")
        rewritten = sum(n.op_type == "Add" and n.input[1].endswith(".fit")
                        for n in onnx.load(str(Path(tmp) / "blocked.onnx")).graph.node)
        export_network(net, Path(tmp) / "model", size)
        runner = AnytimeRunner(Path(tmp) / "model")
        probe_session = probe.session
        probe.session = lambda *a, **k: probe_session(*a, **{**k, "blocked_skips": False})
        try:
            runner_plain = AnytimeRunner(Path(tmp) / "model", handoff=False)
        finally:
            probe.session = probe_session
    diff = max(float(np.abs(a - b).max()) for a, b in zip(plain.run(None, feeds), blocked.run(None, feeds)))
    img, scan = feeds["image"][0], feeds["scan"][0]
    staged_diff = max(float(np.abs(a - b).max()) for a, b in zip(runner.depths(img, scan),
                                                                  runner_plain.depths(img, scan)))
    print(f"block size {probe.block_size()}; {rewritten} skip additions rewritten in the whole graph; max |difference| "
          f"of the depth maps {diff:.2e} (whole graph), {staged_diff:.2e} (staged); tensors the runner hands over "
          f"blocked: {', '.join(runner.handed_off)}")
    whole_t: dict[str, list[float]] = {"as onnxruntime optimises it": [], "blocked skip additions": []}
    staged_t: dict[str, list[float]] = {"neither": [], "blocked skip additions and handoff": []}
    for rep in range(args.reps):   # interleaved
        whole_t["as onnxruntime optimises it"].append(time_call(lambda: plain.run(None, feeds), 3, 40))
        whole_t["blocked skip additions"].append(time_call(lambda: blocked.run(None, feeds), 3, 40))
        staged_t["neither"].append(time_call(lambda: runner_plain.run(img, scan), 3, 40))
        staged_t["blocked skip additions and handoff"].append(time_call(lambda: runner.run(img, scan), 3, 40))
        print(f"  rep {rep + 1}: "
              + ", ".join(f"{k} {v[-1]:.2f} ms" for t in (whole_t, staged_t) for k, v in t.items()))
    report(whole_t, "paper design whole graph at 224x224")
    report(staged_t, "staged runtime at 224x224")
