"""Thread pools for the staged runtime (issue 11): the paper design's stage graphs chained, and its
whole graph, with one intra-op pool per session (spinning off, what explorer.deploy.runtime did before), a
pool per session with spinning on, onnxruntime's global thread pool shared by every session (what
``explorer.probe.session`` does now), and a pool
per session without the NCHWc layout transforms (what the stage boundaries cost them). A
process can use the global pool only for all its sessions, so each variant runs in its own fresh
process (staged and whole interleaved call by call), alternating, --reps times; every repetition
and the medians are printed, with the staged overhead over the whole graph per variant.

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


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--child", nargs=2, metavar=("DIR", "VARIANT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(*_chain_ms(Path(args.child[0]), args.child[1], args.threads))
        raise SystemExit(0)
    from explorer.deploy.export import export_network
    from explorer.model import build_network
    from explorer.model.onnx import export_whole
    from explorer.space import paper_candidate
    variants = [v for v in args.variants.split(",") if v in VARIANTS]
    staged: dict[str, list[float]] = {v: [] for v in variants}
    whole: dict[str, list[float]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        net = build_network(paper_candidate())
        export_network(net, Path(tmp), (224, 224), devices=("tx2",))
        (Path(tmp) / "whole.onnx").write_bytes(export_whole(net, (224, 224)))
        for rep in range(args.reps):
            for variant in variants:   # alternating fresh processes
                out = subprocess.run([sys.executable, __file__, "--threads", str(args.threads), "--child", tmp,
                                      variant], capture_output=True, text=True, check=True)
                s, w = (float(x) for x in out.stdout.strip().splitlines()[-1].split())
                staged[variant].append(s)
                whole[variant].append(w)
            print(f"rep {rep + 1}: " + ", ".join(f"{v} staged {staged[v][-1]:.2f} / whole {whole[v][-1]:.2f} ms "
                                                 f"({staged[v][-1] / whole[v][-1] - 1:+.1%})" for v in variants),
                  flush=True)
    med = statistics.median
    print(f"medians ({args.threads} threads, paper design at 224x224): " + ", ".join(
        f"{v} staged {med(staged[v]):.2f} / whole {med(whole[v]):.2f} ms, overhead "
        f"{med(s / w for s, w in zip(staged[v], whole[v])) - 1:+.1%}" for v in variants))
