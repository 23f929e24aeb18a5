"""What keeping the decoder's skip additions in onnxruntime's blocked layout saves: the paper design's
whole graph as every session of the package makes it (``session``, which rewrites the skip additions:
``explorer.probe.blocked_skip_adds``) against the same graph as onnxruntime optimises it
(``blocked_skips=False``); and the staged runtime, whose stages also hand their skips over blocked,
against one built with neither. Layout conversions around each skip addition cost memory traffic; the
ratios say how much of it the rewrite removes.

    python benchmarks/bench_blocked_skip.py [--reps 7]

The four variants are timed in interleaved blocks in each repetition; the depth maps are compared
(largest difference in the record's notes).
"""

import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch

import explorer.probe as probe
from explorer.calibration.measure import session
from explorer.deploy.export import export_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.space import paper_candidate

from harness import Bench, time_interleaved

SIZE = (224, 224)


def _unblocked_runner(model_dir: Path) -> AnytimeRunner:
    """A runner whose sessions keep onnxruntime's own layout at skip additions and hand nothing over
    blocked (``deploy.sessions.session`` calls ``probe.session`` by attribute, so patching it reaches them)."""
    probe_session = probe.session
    probe.session = lambda *a, **k: probe_session(*a, **{**k, "blocked_skips": False})
    try:
        return AnytimeRunner(model_dir, handoff=False)
    finally:
        probe.session = probe_session


def _largest_difference(a, b) -> float:
    return max(float(np.abs(x - y).max()) for x, y in zip(a, b))


if __name__ == "__main__":
    bench = Bench(__file__, "Blocked-layout skip additions: whole graph and staged runtime", __doc__, reps=7)
    args = bench.parse_args(bench.parser())
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    whole = export_whole(net, SIZE)
    feeds = {k: v.numpy() for k, v in example_inputs(SIZE).items()}
    with tempfile.TemporaryDirectory() as tmp:
        plain = session(whole, blocked_skips=False)
        blocked = session(whole, save_optimized=Path(tmp) / "blocked.onnx")
        rewritten = sum(n.op_type == "Add" and n.input[1].endswith(".fit")
                        for n in onnx.load(str(Path(tmp) / "blocked.onnx")).graph.node)
        export_network(net, Path(tmp) / "model", SIZE)
        runner = AnytimeRunner(Path(tmp) / "model")
        runner_plain = _unblocked_runner(Path(tmp) / "model")
    img, scan = feeds["image"][0], feeds["scan"][0]
    whole_diff = _largest_difference(plain.run(None, feeds), blocked.run(None, feeds))
    staged_diff = _largest_difference(runner.depths(img, scan), runner_plain.depths(img, scan))
    bench.note(f"onnxruntime block size {probe.block_size()}; {rewritten} skip additions rewritten in the whole "
               f"graph; largest depth difference {whole_diff:.1e} (whole graph), {staged_diff:.1e} (staged); "
               f"handed over blocked: {', '.join(runner.handed_off) or 'nothing'}")
    fns = {"whole_plain": lambda: plain.run(None, feeds), "whole_blocked": lambda: blocked.run(None, feeds),
           "staged_plain": lambda: runner_plain.run(img, scan), "staged_blocked": lambda: runner.run(img, scan)}
    bench.figure("whole_plain_ms", "whole graph as onnxruntime optimises it", "ms", "lower")
    bench.figure("whole_blocked_ms", "whole graph with blocked skip additions", "ms", "lower")
    bench.figure("whole_speedup", "whole graph: plain / blocked", "x", "higher")
    bench.figure("staged_plain_ms", "staged runtime with neither", "ms", "lower")
    bench.figure("staged_blocked_ms", "staged runtime with blocked skips and handoff", "ms", "lower")
    bench.figure("staged_speedup", "staged runtime: plain / blocked", "x", "higher")
    for rep in bench.repetitions():
        ms = time_interleaved(fns, rep, blocks=5, per_block=8)
        for kind in ("whole", "staged"):
            bench.add(f"{kind}_plain_ms", ms[f"{kind}_plain"])
            bench.add(f"{kind}_blocked_ms", ms[f"{kind}_blocked"])
            bench.add(f"{kind}_speedup", ms[f"{kind}_plain"] / ms[f"{kind}_blocked"])
    bench.finish()
