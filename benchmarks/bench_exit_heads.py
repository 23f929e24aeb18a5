"""What keeping the exit heads' resizes out of onnxruntime's blocked layout saves
(``explorer.model.ops.one_channel_unblocked``): the paper design's whole graph and each exit head
alone, exported with that step and without it, timed in turn.

    .venv/bin/python benchmarks/bench_exit_heads.py [--reps 5]
"""

import argparse
import io
import statistics
from unittest import mock

import numpy as np
import torch

from explorer.cost.measure import session, time_call
from explorer.model import build_network
from explorer.model.exits import ExitHead, ExitHeadConfig
from explorer.onnx_stages import example_inputs, export_whole
from explorer.space import paper_candidate


def _exported(fn, without: bool) -> bytes:
    if not without:
        return fn()
    with mock.patch("explorer.model.exits.one_channel_unblocked", lambda x: x):   # imported there by name
        return fn()


def _head_graph(cfg: ExitHeadConfig, hw: int) -> tuple[bytes, bytes, np.ndarray]:
    torch.manual_seed(0)
    head = ExitHead(cfg).eval()
    x = torch.rand(1, cfg.in_channels, hw, hw)

    def export() -> bytes:
        f = io.BytesIO()
        torch.onnx.export(head, (x,), f, input_names=["x"], output_names=["depth"], dynamo=False)
        return f.getvalue()
    return _exported(export, False), _exported(export, True), x.numpy()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    size = (224, 224)
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    feeds = {k: v.numpy() for k, v in example_inputs(size).items()}
    graphs = {"with": session(_exported(lambda: export_whole(net, size), False)),
              "without": session(_exported(lambda: export_whole(net, size), True))}
    outs = [s.run(None, feeds) for s in graphs.values()]
    same = all(np.allclose(a, b, rtol=1e-4, atol=1e-4) for a, b in zip(*outs))
    times = {k: [] for k in graphs}
    for rep in range(args.reps):   # interleaved
        for k, s in graphs.items():
            times[k].append(time_call(lambda: s.run(None, feeds), 3, 30))
        print(f"  rep {rep + 1}: whole graph {times['with'][-1]:.2f} ms with the unblocked exit resizes, "
              f"{times['without'][-1]:.2f} ms without: {times['without'][-1] / times['with'][-1]:.3f}x")
    w, wo = statistics.median(times["with"]), statistics.median(times["without"])
    ratios = [b / a for a, b in zip(times["with"], times["without"])]
    print(f"paper design whole graph at {size[0]}x{size[1]}, medians of {args.reps}: {w:.2f} ms with, {wo:.2f} ms "
          f"without: {statistics.median(ratios):.3f}x ({min(ratios):.3f}-{max(ratios):.3f}); same outputs: {same}")
    for cin, up, hw in ((256, 16, 14), (64, 8, 28), (32, 4, 56), (32, 2, 112)):
        with_b, without_b, x = _head_graph(ExitHeadConfig(in_channels=cin, depth=1, width=cin, upscale=up), hw)
        pair = [session(with_b), session(without_b)]
        t = [[], []]
        for _ in range(args.reps):
            for s, tt in zip(pair, t):
                tt.append(time_call(lambda: s.run(None, {"x": x}), 5, 100))
        r = [b / a for a, b in zip(*t)]
        print(f"exit head {cin} channels at {hw}x{hw}, x{up}: {1000 * statistics.median(t[0]):.0f} us with, "
              f"{1000 * statistics.median(t[1]):.0f} us without: {statistics.median(r):.2f}x ({min(r):.2f}-{max(r):.2f})")
