"""The runner's two sets of stage sessions (one memory arena shared by all, or an arena each) against
the whole graph, in each state the machine was in while it ran (``explorer.deploy._arena_choice``).
Which set runs faster depends on whether the machine's cores are free or contended, which is why the
runner picks a set per run; this says whether its choice keeps up with the better set in each state.

    python benchmarks/bench_arena_choice.py [--reps 3] [--seconds 60]

Each repetition runs cycles for --seconds; a cycle times the whole graph, the runner as shipped (it
picks a set per run) and the runner held to each set, interleaved, then the whole graph again (a cycle
whose two whole-graph times differ by over 25% is dropped). A cycle is calm where its whole-graph time
is within 25% of the fastest cycle's (over all repetitions), slowed where it is 1.5x or more. Figures
are per repetition and state (a state absent from a repetition gives that figure no value there).
"""

import statistics
import tempfile
import time
from pathlib import Path

import torch

from explorer.calibration.measure import session, time_call
from explorer.deploy.export import export_network
from explorer.deploy.runtime import AnytimeRunner
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.space import paper_candidate

from harness import Bench, rotated

CALM, SLOWED = 1.25, 1.5
SIZE = (224, 224)
RUNNERS = {"runner": "the runner (picks a set per run)", "shared": "held to the shared arena",
           "own": "held to arenas of their own"}


def cycles_for(seconds: float, whole, feeds, runners: dict, rep: int) -> list[tuple[float, dict[str, float]]]:
    """(whole-graph ms, {runner: ms, "shared_share": share of the runner's runs on the shared set})
    for every cycle in which the machine's state held."""
    chooser = runners["runner"].arena_choice
    image, scan = feeds["image"][0], feeds["scan"][0]
    cycles, t0, k = [], time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        before = time_call(lambda: whole.run(None, feeds), 1, 8)
        served = list(chooser.runs)
        timed = {name: time_call(lambda r=runners[name]: r.run(image, scan), 1, 16)
                 for name in rotated(list(runners), rep * 1000 + k)}
        timed["shared_share"] = (chooser.runs[0] - served[0]) / (sum(chooser.runs) - sum(served))
        after = time_call(lambda: whole.run(None, feeds), 1, 8)
        if max(before, after) <= CALM * min(before, after):   # the state held through the cycle
            cycles.append(((before + after) / 2, timed))
        k += 1
    return cycles


def declare(bench: Bench) -> None:
    for state in ("calm", "slowed"):
        bench.figure(f"{state}_whole_ms", f"{state}: whole graph", "ms", "lower")
        for key, label in RUNNERS.items():
            bench.figure(f"{state}_{key}_change", f"{state}: {label} against the whole graph (ratio - 1)", "", "lower")
        bench.figure(f"{state}_shared_share", f"{state}: share of the runner's runs on the shared arena", "", None)
        bench.figure(f"{state}_cycles", f"{state}: cycles", "", None)


def add_states(bench: Bench, cycles: list, fastest: float) -> None:
    for state, keep in (("calm", lambda w: w <= CALM * fastest), ("slowed", lambda w: w >= SLOWED * fastest)):
        rows = [(w, r) for w, r in cycles if keep(w)]
        bench.add(f"{state}_cycles", len(rows))
        if not rows:
            continue
        bench.add(f"{state}_whole_ms", statistics.median(w for w, _ in rows))
        for key in RUNNERS:
            bench.add(f"{state}_{key}_change", statistics.median(r[key] / w - 1 for w, r in rows))
        bench.add(f"{state}_shared_share", statistics.mean(r["shared_share"] for _, r in rows))


if __name__ == "__main__":
    bench = Bench(__file__, "Runner's arena choice against each session set, by machine state", __doc__)
    ap = bench.parser()
    ap.add_argument("--seconds", type=float, default=60.0, help="length of each repetition")
    args = bench.parse_args(ap)
    torch.manual_seed(0)
    net = build_network(paper_candidate()).eval()
    env = {k: v.numpy() for k, v in example_inputs(SIZE).items()}
    feeds = {"image": env["image"], "scan": env["scan"]}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "model"
        export_network(net, out, SIZE)
        whole = session(export_whole(net, SIZE))
        runners = {"runner": AnytimeRunner(out), "shared": AnytimeRunner(out, arenas="shared"),
                   "own": AnytimeRunner(out, arenas="own")}
    if len(runners["runner"].session_sets) < 2:
        raise SystemExit("the sessions here do not share an arena (EXPLORER_ORT_POOL=session?): nothing to compare")
    declare(bench)
    bench.figure("fastest_whole_ms", "fastest cycle's whole graph", "ms", "lower")
    reps = []
    for rep in bench.repetitions():
        reps.append(cycles_for(args.seconds, whole, feeds, runners, rep))
        if reps[-1]:
            bench.add("fastest_whole_ms", min(w for w, _ in reps[-1]))
    if not any(reps):
        raise SystemExit("the machine's state changed within every cycle: nothing to report")
    fastest = min(w for cycles in reps for w, _ in cycles)   # the calm state: judged over all repetitions
    for cycles in reps:
        add_states(bench, cycles, fastest)
    bench.note(f"the runner's runs per set (shared arena, arenas of their own): {runners['runner'].arena_choice.runs}")
    bench.finish()
