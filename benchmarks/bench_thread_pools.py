"""Thread pools for the staged runtime: the paper design's stage graphs chained, and its whole graph,
with one intra-op pool per session (spinning off), a pool per session with spinning on, onnxruntime's
global thread pool shared by every session (what ``explorer.probe.session`` uses), and a pool per
session without the NCHWc layout transforms (what the stage boundaries cost them). Stages that each
wake their own pool pay for it at every boundary; the staged overhead over the whole graph per
variant says which pooling keeps staging cheap.

    python benchmarks/bench_thread_pools.py [--reps 3] [--threads 2] [--variants global,per-session]

A process can use the global pool only for all its sessions, so each variant runs in a fresh process
of its own (staged and whole interleaved call by call); each repetition runs every variant, in an
order that rotates.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import Bench, rotated

VARIANTS = ("per-session", "per-session-spinning", "global", "per-session-no-layout")


def _chain_ms(model_dir: Path, variant: str, threads: int) -> tuple[float, float]:
    """(staged, whole graph) medians in ms, both with this variant's thread pools."""
    import numpy as np
    import onnxruntime as ort
    if variant == "global":
        ort.set_global_thread_pool_sizes(threads, 1)
    manifest = json.loads((model_dir / "manifest.json").read_text())
    sessions = []
    for file in [stage["file"] for stage in manifest["stages"]] + ["whole.onnx"]:
        opts = ort.SessionOptions()
        # no-layout: without the NCHWc layout transforms (ENABLE_EXTENDED), what stage boundaries cost them
        opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED if "no-layout" in variant
                                         else ort.GraphOptimizationLevel.ORT_ENABLE_ALL)
        opts.log_severity_level = 3
        if variant == "global":
            opts.use_per_session_threads = False
        else:
            opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
            opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if "spinning" in variant else "0")
        s = ort.InferenceSession(str(model_dir / file), opts, providers=["CPUExecutionProvider"])
        sessions.append((s, [i.name for i in s.get_inputs()], [o.name for o in s.get_outputs()]))
    h, w = manifest["input_size"]
    rng = np.random.default_rng(0)
    feeds = {"image": rng.random((1, 3, h, w), dtype=np.float32),
             "scan": (rng.random((1, w), dtype=np.float32) * 5).astype(np.float32)}

    whole, stages = sessions[-1][0], sessions[:-1]

    def chain() -> None:
        env = dict(feeds)
        for s, ins, outs in stages:
            env.update(zip(outs, s.run(outs, {n: env[n] for n in ins})))

    samples: dict[str, list[float]] = {"staged": [], "whole": []}
    for fn in (chain, lambda: whole.run(None, feeds)):
        for _ in range(5):
            fn()
    for _ in range(40):   # interleaved call by call
        for name, fn in (("staged", chain), ("whole", lambda: whole.run(None, feeds))):
            t0 = time.perf_counter()
            fn()
            samples[name].append((time.perf_counter() - t0) * 1000)
    return statistics.median(samples["staged"]), statistics.median(samples["whole"])


def child_ms(model_dir: str, variant: str, threads: int) -> tuple[float, float]:
    """(staged, whole) ms of ``variant`` measured in a fresh process."""
    out = subprocess.run([sys.executable, __file__, "--threads", str(threads), "--child", model_dir, variant],
                         capture_output=True, text=True, check=True)
    staged, whole = (float(x) for x in out.stdout.strip().splitlines()[-1].split())
    return staged, whole


if __name__ == "__main__":
    bench = Bench(__file__, "Thread pools for the staged runtime: staged overhead per pooling", __doc__)
    ap = bench.parser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--child", nargs=2, metavar=("DIR", "VARIANT"), help=argparse.SUPPRESS)
    args = bench.parse_args(ap)
    if args.child:
        print(*_chain_ms(Path(args.child[0]), args.child[1], args.threads))
        raise SystemExit(0)
    from explorer.deploy.export import export_network
    from explorer.model import build_network
    from explorer.model.onnx import export_whole
    from explorer.space import paper_candidate
    variants = [v for v in args.variants.split(",") if v in VARIANTS]
    for v in variants:
        bench.figure(f"{v}_staged_ms", f"{v}: staged", "ms", "lower")
        bench.figure(f"{v}_whole_ms", f"{v}: whole graph", "ms", "lower")
        bench.figure(f"{v}_overhead", f"{v}: staged over whole (ratio - 1)", "", "lower")
    bench.note(f"{args.threads} threads, paper design at 224x224")
    with tempfile.TemporaryDirectory() as tmp:
        net = build_network(paper_candidate())
        export_network(net, Path(tmp), (224, 224), devices=("tx2",))
        (Path(tmp) / "whole.onnx").write_bytes(export_whole(net, (224, 224)))
        for rep in bench.repetitions():
            for v in rotated(variants, rep):   # a fresh process each
                staged, whole = child_ms(tmp, v, args.threads)
                bench.add(f"{v}_staged_ms", staged)
                bench.add(f"{v}_whole_ms", whole)
                bench.add(f"{v}_overhead", staged / whole - 1)
    bench.finish()
