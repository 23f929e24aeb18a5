"""Thread pools for the staged runtime (issue 11): the paper design's stage graphs chained with one
intra-op pool per session (spinning off, what explorer.runtime does), a pool per session with
spinning on, and onnxruntime's global thread pool shared by every session. A process can use the
global pool only for all its sessions, so each variant runs in its own fresh process, alternating,
--reps times; every repetition and the medians are printed.

    .venv/bin/python benchmarks/bench_thread_pools.py [--reps 3] [--threads 2]
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

VARIANTS = ("per-session", "per-session-spinning", "global")


def _chain_ms(model_dir: Path, variant: str, threads: int) -> float:
    import numpy as np
    import onnxruntime as ort
    if variant == "global":
        ort.set_global_thread_pool_sizes(threads, 1)
    manifest = json.loads((model_dir / "manifest.json").read_text())
    sessions = []
    for stage in manifest["stages"]:
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        if variant == "global":
            opts.use_per_session_threads = False
        else:
            opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
            opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if "spinning" in variant else "0")
        s = ort.InferenceSession(str(model_dir / stage["file"]), opts, providers=["CPUExecutionProvider"])
        sessions.append((s, [i.name for i in s.get_inputs()], [o.name for o in s.get_outputs()]))
    h, w = manifest["input_size"]
    rng = np.random.default_rng(0)
    feeds = {"image": rng.random((1, 3, h, w), dtype=np.float32),
             "scan": (rng.random((1, w), dtype=np.float32) * 5).astype(np.float32)}

    def chain() -> None:
        env = dict(feeds)
        for s, ins, outs in sessions:
            env.update(zip(outs, s.run(outs, {n: env[n] for n in ins})))

    for _ in range(5):
        chain()
    samples = []
    for _ in range(40):
        t0 = time.perf_counter()
        chain()
        samples.append((time.perf_counter() - t0) * 1000)
    return statistics.median(samples)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--child", nargs=2, metavar=("DIR", "VARIANT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(_chain_ms(Path(args.child[0]), args.child[1], args.threads))
        raise SystemExit(0)
    from explorer.deploy import export_network
    from explorer.model import build_network
    from explorer.space import paper_candidate
    results: dict[str, list[float]] = {v: [] for v in VARIANTS}
    with tempfile.TemporaryDirectory() as tmp:
        export_network(build_network(paper_candidate()), Path(tmp), (224, 224), devices=("tx2",))
        for rep in range(args.reps):
            for variant in VARIANTS:   # alternating fresh processes
                out = subprocess.run([sys.executable, __file__, "--threads", str(args.threads), "--child", tmp,
                                      variant], capture_output=True, text=True, check=True)
                results[variant].append(float(out.stdout.strip().splitlines()[-1]))
            print(f"rep {rep + 1}: " + ", ".join(f"{v} {results[v][-1]:.2f} ms" for v in VARIANTS), flush=True)
    print("medians: " + ", ".join(f"{v} {statistics.median(results[v]):.2f} ms" for v in VARIANTS)
          + f" (paper design's stage graphs chained at 224x224, {args.threads} threads)")
