"""The runner's two sets of stage sessions (one memory arena shared by all, or an arena each) against
the whole graph, in each state the machine was in while it ran (`explorer.deploy._arena_choice`).

A shared 2-core VM switches from outside between states (on the Zen 4 VM: calm, the paper design's
whole graph at 7.7 ms; slowed, 13.9 ms, where two threads run it no faster than one), so the figures
are grouped by state: each cycle times the whole graph, the runner as shipped (it picks a set per run),
and the runner held to each set, interleaved; a cycle is calm where its whole-graph time is within
25% of the fastest cycle's, slowed where it is 1.5x or more. --blocks repetitions of --seconds each;
every repetition's medians, then the medians over all cycles.

    .venv/bin/python benchmarks/bench_arena_choice.py [--blocks 3] [--seconds 60]
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from explorer.calibration.measure import session, time_call
from explorer.deploy.export import export_network
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.deploy.runtime import AnytimeRunner
from explorer.space import paper_candidate

CALM, SLOWED = 1.25, 1.5
SHARED_SHARE = "share of the runner's runs on the shared arena's set"


def report(label: str, cycles: list[tuple[float, dict[str, float]]], fastest: float) -> None:
    for state, keep in (("calm", lambda w: w <= CALM * fastest), ("slowed", lambda w: w >= SLOWED * fastest)):
        rows = [(w, r) for w, r in cycles if keep(w)]
        if not rows:
            print(f"  {label} {state}: no cycle")
            continue
        print(f"  {label} {state}: {len(rows)} cycles, whole graph {statistics.median(w for w, _ in rows):.2f} ms; "
              + "; ".join(f"{k} {statistics.median(r[k] / w - 1 for w, r in rows):+.1%}" for k in rows[0][1]
                          if k != SHARED_SHARE)
              + f"; the runner ran the shared arena's set in {statistics.mean(r[SHARED_SHARE] for _, r in rows):.0%} "
                "of its runs")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    size = (224, 224)
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    env = {k: v.numpy() for k, v in example_inputs(size).items()}
    feeds = {"image": env["image"], "scan": env["scan"]}
    image, scan = env["image"][0], env["scan"][0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "model"
        export_network(net, out, size)
        whole = session(export_whole(net, size))
        runners = {"runner (picks a set per run)": AnytimeRunner(out),
                   "held to the shared arena": AnytimeRunner(out, arenas="shared"),
                   "held to arenas of their own": AnytimeRunner(out, arenas="own")}
        if len(runners["runner (picks a set per run)"].session_sets) < 2:
            raise SystemExit("the sessions here do not share an arena (EXPLORER_ORT_POOL=session?): nothing to compare")
        chooser = runners["runner (picks a set per run)"].arena_choice
        blocks: list[list[tuple[float, dict[str, float]]]] = []
        for b in range(args.blocks):
            cycles = []
            t0 = time.monotonic()
            while time.monotonic() - t0 < args.seconds:
                before = time_call(lambda: whole.run(None, feeds), 1, 8)
                served = list(chooser.runs)
                timed = {k: time_call(lambda: r.run(image, scan), 1, 16) for k, r in runners.items()}
                timed[SHARED_SHARE] = (chooser.runs[0] - served[0]) / (sum(chooser.runs) - sum(served))
                after = time_call(lambda: whole.run(None, feeds), 1, 8)
                if max(before, after) <= CALM * min(before, after):   # the state held through the cycle
                    cycles.append(((before + after) / 2, timed))
            blocks.append(cycles)
        fastest = min(w for cycles in blocks for w, _ in cycles)
        print(f"staged over the whole graph, by the machine's state (fastest whole graph {fastest:.2f} ms), "
              f"{args.blocks} repetitions of {args.seconds:.0f} s:")
        for b, cycles in enumerate(blocks, start=1):
            report(f"rep {b}", cycles, fastest)
        report("all reps", [c for cycles in blocks for c in cycles], fastest)
        print(f"the runner's runs per set (shared arena, arenas of their own): {chooser.runs}")
