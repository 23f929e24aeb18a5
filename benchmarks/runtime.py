"""The runtime suite: deployment speed on this machine.

- ``runtime``: the anytime runtime, staged against one whole graph, onnxruntime against PyTorch eager,
  int8 against fp32, and the profile's predictions against the measured ready times;
- ``path0``: path 0's fill (nearest return per column) as passes against a distance-matrix search,
  over a grid of image sizes;
- ``blocked_skip``: decoder skips read from blocked layouts against plain ones;
- ``int8_layers``: each kind of layer in int8 against fp32.

    python -m benchmarks.runtime --list
    python -m benchmarks.runtime --only path0 [--reps 5] [--size 224x224]
"""

from __future__ import annotations

import io
import os
import statistics
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Callable, NamedTuple, Sequence, TypeVar

import numpy as np
import onnx
import torch
from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

import explorer.probe as probe
from explorer.anytime import anytime_loss
from explorer.calibration.calibrate import calibrate, read_results
from explorer.calibration.measure import session, time_call
from explorer.calibration.peak import gemm_gmacs, host_peak
from explorer.calibration.sweep import SweepLayer, layer_graph
from explorer.cost import candidate_cost
from explorer.data import open_dataset
from explorer.deploy.export import Quantization, export_network
from explorer.deploy.int8_graphs import _Feeds
from explorer.deploy.runtime import AnytimeRunner, measured_anytime
from explorer.metrics import MetricAverager, depth_metrics
from explorer.model import build_network
from explorer.model.exits import interpolate_scan
from explorer.model.onnx import example_inputs, export_whole
from explorer.probe import (DEFAULT_PROVIDER, default_threads, fixed_graph_timer, REMEASURE_PASSES, SLOW,
                            speed_layer, usual_speed, wait_until_calm)
from explorer.space import paper_candidate
from explorer.training.train import TrainConfig, train

from benchmarks.harness import Bench, Case, grid, image_size, interleave, run_suite, suffix, time_interleaved


# -- steady ----------------------------------------------------------------------------------------

# Measurements taken at the speed a calibration measured at. A machine whose speed changes from outside
# (other loads, throttling) can run every graph much slower for a while; a timing taken in such a spell
# says nothing about a profile fitted while it ran at its usual speed. The rule is the probe's own
# (``SLOW``, ``REMEASURE_PASSES``, ``wait_until_calm`` of ``explorer.probe``); ``note_steadiness`` puts
# what the rule did into the record.

T = TypeVar("T")


def speedometer(bundle: Path, results: dict) -> Callable[[], float]:
    """How much slower than during its calibration the machine runs now (1 = its usual speed then):
    the probe's two speed-check graphs (from the calibration's ``bundle`` and ``results``) timed
    again, each against its usual time in the calibration; the slower of the two."""
    speed = results["speed"]
    graphs = [(speed_layer(results["bundle"]["layers"])["file"], speed["ms"]), (speed["stage"], speed["stage_ms"])]
    timers = [(fixed_graph_timer(bundle / file, default_threads(), DEFAULT_PROVIDER), usual_speed(times))
              for file, times in graphs if file and times]
    return lambda: max(timer() / usual for timer, usual in timers)


class Steady(NamedTuple):
    """What ``steadily`` took: the result, how many times it was taken again, and how much slower than
    during the calibration the machine ran around the last time (the slower of the two checks; above
    ``1 + SLOW`` when it stayed slow past the re-timing, and the result with it)."""

    result: object
    again: int
    slowness: float

    def note(self) -> str:
        """'' at the calibration's speed, else a few words saying how slow the machine still ran."""
        return "" if self.slowness <= 1 + SLOW else f" (machine {self.slowness:.2f}x slow)"


def steadily(measure: Callable[[], T], slowness: Callable[[], float],
             combine: Callable[[T, T], T] = lambda kept, new: new) -> Steady:
    """``measure()`` between two ``slowness`` checks; taken again (after waiting for the machine to calm
    down) while either check ran ``SLOW`` or more slower than usual, at most ``REMEASURE_PASSES`` times.
    ``combine`` folds a new result into the kept one (default: the new one replaces it)."""
    kept = None
    for again in range(REMEASURE_PASSES + 1):
        before = slowness()
        got = measure()
        after = slowness()
        kept = got if kept is None else combine(kept, got)
        if max(before, after) <= 1 + SLOW or again == REMEASURE_PASSES:
            return Steady(kept, again, max(before, after))
        wait_until_calm(after, slowness, 1.0)
    raise AssertionError("unreachable")


def note_steadiness(bench, what: str, taken: Sequence[Steady]) -> None:
    """Notes in ``bench``'s record (a ``harness.Bench``) how often ``what`` was taken again, and how
    many of its results were still taken on a slow machine: a reader of the figures needs to know."""
    again = sum(s.again for s in taken)
    slow = sum(bool(s.note()) for s in taken)
    if again or slow:
        bench.note(f"{what}: taken again {again} times after the machine ran slow; {slow} of {len(taken)} still slow")


# -- runtime ----------------------------------------------------------------------------------

SIZE = (224, 224)


FP32 = {"whole": "whole graph", "staged": "staged", "deadline": "staged with a deadline",
        "no_handoff": "staged without the handoff", "bare_chain": "the stage sessions alone",
        "shared_arena": "staged held to the shared arena", "own_arenas": "staged held to arenas of their own",
        "eager": "PyTorch eager"}


INT8 = {"int8_fp32": "staged fp32", "int8": "staged int8 (the export's choice)",
        "int8_no_handoff": "staged int8 without the uint8 handoff", "int8_all": "staged int8, every stage",
        "int8_eager": "PyTorch eager (fp32)"}


def trained_net(steps: int):
    torch.manual_seed(0)
    net = build_network(paper_candidate())
    cfg = TrainConfig(steps=steps, batch_size=16, input_size=(64, 64))
    train(net, open_dataset("synthetic", "train", (64, 64)), open_dataset("synthetic:48:16", "val", (64, 64)), cfg,
          val_limit=16)
    return net.eval()


def fp32_calls(net, out: Path, feeds: dict) -> tuple[dict, AnytimeRunner]:
    """{variant: call} of the fp32 variants, and the runner as shipped."""
    runner = AnytimeRunner(out)
    plain = AnytimeRunner(out, handoff=False)
    shared_only, own_only = AnytimeRunner(out, arenas="shared"), AnytimeRunner(out, arenas="own")
    whole = session(export_whole(net, SIZE))
    image, scan = feeds["image"][0], feeds["scan"][0]
    img_t, scan_t = torch.from_numpy(feeds["image"]), torch.from_numpy(feeds["scan"])

    def bare_chain():  # the stage sessions alone: no input checks, deadline timer or halting
        values = dict(feeds)
        for _, sess, ins, outs in runner.sessions:
            values.update(zip(outs, sess.run(outs, {n: values[n] for n in ins})))

    def eager():
        with torch.no_grad():
            net(img_t, scan_t)
    return {"whole": lambda: whole.run(None, feeds), "staged": lambda: runner.run(image, scan),
            "deadline": lambda: runner.run(image, scan, 1e4), "no_handoff": lambda: plain.run(image, scan),
            "bare_chain": bare_chain, "shared_arena": lambda: shared_only.run(image, scan),
            "own_arenas": lambda: own_only.run(image, scan), "eager": eager}, runner


def int8_calls(bench: Bench, net, out: Path, runner, eager, feeds: dict) -> tuple[dict, AnytimeRunner]:
    """{variant: call} of the int8 comparison; notes what each export chose and its RMSE change."""
    q8 = out / "int8"
    m = export_network(net, q8, SIZE, quantization=Quantization(data="synthetic", max_degradation=1.0))
    m_all = export_network(net, out / "int8-all", SIZE,
                           quantization=Quantization(data="synthetic", max_degradation=1.0, stages="all"))
    runner8 = AnytimeRunner(q8)
    variants = {"int8_fp32": runner, "int8": runner8, "int8_no_handoff": AnytimeRunner(q8, handoff=False),
                "int8_all": AnytimeRunner(out / "int8-all")}
    bench.note("int8 export's stages: " + "; ".join(f"{st.name} {st.precision}" for st in m.stages))
    for key, mm in (("int8", m), ("int8_all", m_all)):
        deg = mm.quantization.rmse_degradation
        bench.add(bench.figure(f"{key}_last_path_rmse_change", f"{INT8[key]}: last path RMSE change", "", "lower"),
                  deg[-1])
        bench.note(f"{INT8[key]}: RMSE change per path {' '.join(f'{100 * d:+.1f}%' for d in deg)} on "
                   f"{mm.quantization.evaluation.frames} frames; handed over: "
                   + (", ".join(f"{n} ({f})" for n, f in variants[key].handed_off.items()) or "none"))
    image, scan = feeds["image"][0], feeds["scan"][0]
    return {**{k: (lambda r=r: r.run(image, scan)) for k, r in variants.items()}, "int8_eager": eager}, runner8


def declare(bench: Bench, int8: bool, anytime: bool, paths: int) -> None:
    for k, label in FP32.items():
        bench.figure(f"{k}_ms", label, "ms", "lower")
    bench.figure("staged_overhead", "staged over the whole graph (ratio - 1)", "", "lower")
    bench.figure("eager_over_whole", "PyTorch eager / onnxruntime whole graph", "x", "higher")
    bench.figure("whole_gmacs", "whole graph throughput", "GMAC/s", "higher")
    bench.figure("whole_peak_fraction", "whole graph share of nominal fp32 peak", "", "higher")
    bench.figure("gemm_gmacs", "1024^3 fp32 matrix product in onnxruntime", "GMAC/s", "higher")
    if int8:
        for k, label in INT8.items():
            bench.figure(f"{k}_ms", label, "ms", "lower")
        bench.figure("int8_speedup", "staged fp32 / staged int8", "x", "higher")
        bench.figure("int8_all_speedup", "staged fp32 / staged int8 every stage", "x", "higher")
        bench.figure("int8_over_eager", "PyTorch eager / staged int8", "x", "higher")
    for label in ("fp32", "int8") if anytime else ():
        if label == "int8" and not int8:
            continue
        for p in range(1, paths):
            bench.figure(f"{label}_path{p}_ready_error", f"{label} path {p} ready time: predicted / measured - 1", "",
                         None)
    if anytime:
        bench.figure("anytime_loss_gap", "measured anytime loss / predicted - 1", "", None)


def ready_times(runner, image, scan, paths: int) -> list[float]:
    """Each path's median ready time over 20 whole runs."""
    ready = [[] for _ in range(paths)]
    for _ in range(20):
        for path, ms in runner.run(image, scan).completed:
            ready[path].append(ms)
    return [statistics.median(t) for t in ready]


def path_losses(net, frames) -> list[float]:
    per_path = [MetricAverager() for _ in range(paper_candidate().num_paths)]
    with torch.no_grad():
        for f in frames:
            for p, o in enumerate(net(f["image"][None], f["scan"][None], f["scan_row"])):
                per_path[p].add(depth_metrics(o[0, 0], f["depth"][0]))
    return [a.result()["rmse"] for a in per_path]


def prepare_anytime(bench: Bench, out: Path, net, args, runners: dict) -> dict:
    """The host profile (a calibration, kept with its bundle for the speed checks), its predictions,
    and the frames and deadlines the measured anytime loss is taken on."""
    cand = paper_candidate()
    prof = calibrate(results_out=out / "calibration.json", bundle_out=out / "calibration-bundle")
    slowness = speedometer(out / "calibration-bundle", read_results(out / "calibration.json"))
    pred_ms = candidate_cost(cand, SIZE).path_latency_ms(prof)
    ds = open_dataset("synthetic", "val", SIZE, train_augment=False)
    frames = [ds[i] for i in range(args.frames)]
    b_max = 1.25 * pred_ms[-1]
    predicted_cands = {"fp32": cand, "int8": replace(cand, precision="int8")}
    bench.note(f"predicted path times (host profile): {' '.join(f'{x:.2f}' for x in pred_ms[1:])} ms; anytime loss "
               f"over U(0, {b_max:.1f} ms) on {args.frames} frames, {args.deadlines} deadlines")
    return {"slowness": slowness, "frames": frames, "grid": (np.arange(args.deadlines) + 0.5) * b_max / args.deadlines,
            "predicted_loss": anytime_loss(pred_ms, path_losses(net, frames), f"time:uniform:{b_max}ms"),
            "predicted_ms": {k: candidate_cost(c, SIZE).path_latency_ms(prof) for k, c in predicted_cands.items()
                             if k in runners},
            "runners": runners, "taken": []}


def timing_rep(bench: Bench, rep: int, fp32: dict, int8: dict, macs: float, peak) -> None:
    ms = time_interleaved(fp32, rep, blocks=5)
    for k in FP32:
        bench.add(f"{k}_ms", ms[k])
    w = ms["whole"]
    bench.add("staged_overhead", ms["staged"] / w - 1)
    bench.add("eager_over_whole", ms["eager"] / w)
    bench.add("whole_gmacs", macs / (w * 1e6))
    bench.add("whole_peak_fraction", peak.fraction(macs, w))
    bench.add("gemm_gmacs", gemm_gmacs(reps=1)[0])
    if int8:
        ms = time_interleaved(int8, rep, blocks=5)
        for k in INT8:
            bench.add(f"{k}_ms", ms[k])
        bench.add("int8_speedup", ms["int8_fp32"] / ms["int8"])
        bench.add("int8_all_speedup", ms["int8_fp32"] / ms["int8_all"])
        bench.add("int8_over_eager", ms["int8_eager"] / ms["int8"])


def anytime_rep(bench: Bench, ctx: dict, image, scan) -> None:
    """Each runner's path ready times against the profile's predictions, and the fp32 runner's measured
    anytime loss against the predicted one, each taken at the calibration's speed."""
    paths = paper_candidate().num_paths
    for label, runner in ctx["runners"].items():
        got = steadily(lambda: ready_times(runner, image, scan, paths), ctx["slowness"])
        ctx["taken"].append(got)
        for p in range(1, paths):   # path 0 is ready at once: nothing to compare
            bench.add(f"{label}_path{p}_ready_error", ctx["predicted_ms"][label][p] / got.result[p] - 1)
    got = steadily(lambda: measured_anytime(ctx["runners"]["fp32"], ctx["frames"], ctx["grid"])["anytime_loss"],
                   ctx["slowness"])
    ctx["taken"].append(got)
    bench.add("anytime_loss_gap", got.result / ctx["predicted_loss"] - 1)


def bench_runtime(argv: Sequence[str] | None = None) -> None:
    """Deployment on this machine: staged execution against one whole graph, onnxruntime against PyTorch
    eager, int8 against fp32 (speed and each path's RMSE; the export's own choice of int8 stages, the same
    without the uint8 handoff between int8 stages, and every stage int8), and the path ready times and
    anytime loss measured against what the host profile predicts. These are the deployment claims: staging
    costs little over the whole graph, onnxruntime beats eager, int8 pays, and the profile predicts.

        python -m benchmarks.runtime --only runtime [--reps 5] [--frames 16] [--deadlines 40] [--train-steps 100]
            [--skip-int8] [--skip-anytime]

    Each repetition times every variant in interleaved blocks whose order rotates, then (unless
    --skip-anytime) the ready times and the anytime loss, taken at the speed the host calibration
    measured at (``steadily``: taken again while the machine ran slow).
    """
    bench = Bench("bench_runtime", "Deployment: staged against whole graph, onnxruntime against eager, int8, "
                  "profile predictions", bench_runtime.__doc__, reps=5)
    ap = bench.parser()
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--deadlines", type=int, default=40)
    ap.add_argument("--train-steps", type=int, default=100)
    ap.add_argument("--skip-anytime", action="store_true", help="only the staged, eager and int8 timings")
    ap.add_argument("--skip-int8", action="store_true", help="no int8 export and timing")
    args = bench.parse_args(ap, argv)
    net = trained_net(args.train_steps)
    env = {k: v.numpy() for k, v in example_inputs(SIZE).items()}
    feeds = {"image": env["image"], "scan": env["scan"]}
    peak = host_peak()
    macs = candidate_cost(paper_candidate(), SIZE).path_params_macs()[-1][1]
    bench.note(f"this machine's peak: {peak.describe()}; whole graph {macs / 1e9:.3f} GMAC; "
               f"PyTorch {torch.get_num_threads()} threads")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        export_network(net, out, SIZE)
        fp32, runner = fp32_calls(net, out, feeds)
        int8, runner8 = ({}, None) if args.skip_int8 else int8_calls(bench, net, out, runner, fp32["eager"], feeds)
        declare(bench, not args.skip_int8, not args.skip_anytime, paper_candidate().num_paths)
        runners = {"fp32": runner, **({"int8": runner8} if runner8 else {})}
        ctx = None if args.skip_anytime else prepare_anytime(bench, out, net, args, runners)
        for rep in bench.repetitions():
            timing_rep(bench, rep, fp32, int8, macs, peak)
            if ctx:
                anytime_rep(bench, ctx, feeds["image"][0], feeds["scan"][0])
        bench.note(f"the runner's runs per session set (shared arena, arenas of their own): {runner.arena_choice.runs}")
        if ctx:
            note_steadiness(bench, "ready times and anytime loss", ctx["taken"])
    bench.finish()


# -- path0 ------------------------------------------------------------------------------------

SIZES = ("224x224", "224x320", "192x640")   # the calibration sizes: path0's grid


def _by_search(scan: torch.Tensor, height: int) -> torch.Tensor:
    """The search the passes replace: distances to every column, missing ones pushed away, argmin."""
    n, w = scan.shape
    cols = torch.arange(w, dtype=scan.dtype)
    distance = (cols[:, None] - cols[None, :]).abs()
    invalid = (scan <= 0).to(scan.dtype) * (4.0 * w)
    nearest = (distance[None] + invalid[:, None, :]).argmin(dim=2)
    return torch.gather(scan, 1, nearest)[:, None, None, :].expand(n, 1, height, w)


class _Path0(torch.nn.Module):
    def __init__(self, fill, height: int) -> None:
        super().__init__()
        self.fill, self.height = fill, height

    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        return self.fill(scan, self.height)


def _graph(fill, height: int, width: int) -> bytes:
    buf = io.BytesIO()
    torch.onnx.export(_Path0(fill, height), (torch.rand(1, width),), buf, opset_version=17, dynamo=False,
                      input_names=["scan"])
    return buf.getvalue()


def _variants(h: int, w: int, rng) -> dict:
    """{variant: call} for one size; raises if the two fills disagree."""
    scan = rng.uniform(0.5, 10.0, (1, w)).astype(np.float32)
    scan[rng.random((1, w)) < 0.5] = 0.0   # half the columns without a return
    t = torch.from_numpy(scan)
    fills = {"search": _by_search, "passes": interpolate_scan}
    sessions = {k: session(_graph(f, h, w)) for k, f in fills.items()}
    if not np.array_equal(*(s.run(None, {"scan": scan})[0] for s in sessions.values())):
        raise SystemExit(f"{h}x{w}: the search and the passes give different maps")
    return {**{f"ort_{k}": (lambda s=s: s.run(None, {"scan": scan})) for k, s in sessions.items()},
            **{f"torch_{k}": (lambda f=f: f(t, h)) for k, f in fills.items()}}


def bench_path0(argv: Sequence[str] | None = None) -> None:
    """Path 0 as a stage (``scan_fill``, what residual exits correct): each column's nearest return found in
    a few passes over the columns (``explorer.model.exits.interpolate_scan``) against a search of a W x W
    matrix of column distances, in onnxruntime (the graph the runtime runs) and in PyTorch, at the widths
    of the three calibration sizes. The passes exist because the search's cost grows with W squared; the
    ratio per repetition says what they save.

        python -m benchmarks.runtime --only path0 [--reps 5]

    Every size's four variants are timed in interleaved blocks in each repetition; the two fills must
    give the same maps.
    """
    bench = Bench("bench_path0", "Path 0 (nearest return per column): passes against a distance-matrix search",
                  bench_path0.__doc__, reps=5)
    ap = bench.parser()
    ap.add_argument("--size", action="append", choices=SIZES, help="a size of the grid (default all)")
    args = bench.parse_args(ap, argv)
    rng = np.random.default_rng(0)
    cases = {suffix(p): _variants(*image_size(p["size"]), rng) for p in grid(size=args.size or SIZES)}
    for size in cases:
        for runtime, name in (("ort", "onnxruntime"), ("torch", "PyTorch")):
            for fill in ("passes", "search"):
                bench.figure(f"{runtime}_{fill}_us_{size}", f"{name} {fill} at {size}", "us", "lower")
            bench.figure(f"{runtime}_search_over_passes_{size}", f"{name} search / passes at {size}", "x", "higher")
    for rep in bench.repetitions():
        for size, fns in cases.items():
            ms = time_interleaved(fns, rep, blocks=10, per_block=20)
            for runtime in ("ort", "torch"):
                bench.add(f"{runtime}_passes_us_{size}", 1000 * ms[f"{runtime}_passes"])
                bench.add(f"{runtime}_search_us_{size}", 1000 * ms[f"{runtime}_search"])
                bench.add(f"{runtime}_search_over_passes_{size}", ms[f"{runtime}_search"] / ms[f"{runtime}_passes"])
    bench.finish()


# -- blocked_skip -----------------------------------------------------------------------------



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


def bench_blocked_skip(argv: Sequence[str] | None = None) -> None:
    """What keeping the decoder's skip additions in onnxruntime's blocked layout saves: the paper design's
    whole graph as every session of the package makes it (``session``, which rewrites the skip additions:
    ``explorer.probe.blocked_skip_adds``) against the same graph as onnxruntime optimises it
    (``blocked_skips=False``); and the staged runtime, whose stages also hand their skips over blocked,
    against one built with neither. Layout conversions around each skip addition cost memory traffic; the
    ratios say how much of it the rewrite removes.

        python -m benchmarks.runtime --only blocked_skip [--reps 7]

    The four variants are timed in interleaved blocks in each repetition; the depth maps are compared
    (largest difference in the record's notes).
    """
    bench = Bench("bench_blocked_skip", "Blocked-layout skip additions: whole graph and staged runtime",
                  bench_blocked_skip.__doc__, reps=7)
    bench.parse_args(bench.parser(), argv)
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


# -- int8_layers ------------------------------------------------------------------------------



LAYERS = [
    ("stem_224", "stem 3->32 3x3 s2 at 224x224", SweepLayer("conv", (3, 224, 224), 32, 3, 2)),
    ("dw3_112x32", "depthwise 3x3 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 3, 1)),
    ("dw3_14x512", "depthwise 3x3 at 14x14x512", SweepLayer("depthwise", (512, 14, 14), 512, 3, 1)),
    ("dw5_28x768", "depthwise 5x5 at 28x28x768", SweepLayer("depthwise", (768, 28, 28), 768, 5, 1)),
    ("dw5_112x32", "depthwise 5x5 at 112x112x32", SweepLayer("depthwise", (32, 112, 112), 32, 5, 1)),
    ("pw16_8_224", "pointwise 16->8 at 224x224", SweepLayer("pointwise", (16, 224, 224), 8)),
    ("pw32_16_112", "pointwise 32->16 at 112x112", SweepLayer("pointwise", (32, 112, 112), 16)),
    ("pw64_128_56", "pointwise 64->128 at 56x56", SweepLayer("pointwise", (64, 56, 56), 128)),
    ("pw512_512_14", "pointwise 512->512 at 14x14", SweepLayer("pointwise", (512, 14, 14), 512)),
    ("pw768_64_28", "pointwise 768->64 at 28x28", SweepLayer("pointwise", (768, 28, 28), 64)),
]


def quantized(model: bytes, feeds: dict) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "f.onnx", Path(tmp) / "q.onnx"
        src.write_bytes(model)
        quantize_static(str(src), str(dst), _Feeds([feeds]), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        reduce_range=True, calibrate_method=CalibrationMethod.MinMax)
        return dst.read_bytes()


def bench_int8_layers(argv: Sequence[str] | None = None) -> None:
    """Which layers int8 pays for on this machine: single-layer graphs of the paper design's kinds and
    sizes, each timed in float and quantized as ``explorer export --quantize int8`` quantizes (static QDQ,
    7-bit per-channel weights, uint8 activations, the quantize / dequantize at its input and output
    included). An export quantizes whole stage graphs, where a layer pays these edges only at the graph's
    own (``explorer.deploy.quantize``); this shows what each kind costs alone, which is what decides
    where int8 stages are worth keeping.

        python -m benchmarks.runtime --only int8_layers [--reps 3] [--threads 2]

    Every layer in both precisions is timed in each repetition, in an order that rotates between
    repetitions.
    """
    os.environ.setdefault("EXPLORER_ORT_POOL", "session")   # quantize_static makes sessions of its own
    bench = Bench("bench_int8_layers", "int8 against fp32 per layer kind", bench_int8_layers.__doc__)
    ap = bench.parser()
    ap.add_argument("--threads", type=int, default=2)
    args = bench.parse_args(ap, argv)
    calls = {}
    for key, label, layer in LAYERS:
        model, feeds, _ = layer_graph(layer)
        fp32, int8 = session(model, args.threads), session(quantized(model, feeds), args.threads)
        calls[f"{key}_fp32"] = lambda s=fp32, f=feeds: time_call(lambda: s.run(None, f), 3, 25)
        calls[f"{key}_int8"] = lambda s=int8, f=feeds: time_call(lambda: s.run(None, f), 3, 25)
        bench.figure(f"{key}_fp32_ms", f"{label} fp32", "ms", "lower")
        bench.figure(f"{key}_int8_ms", f"{label} int8", "ms", "lower")
        bench.figure(f"{key}_int8_over_fp32", f"{label} int8 / fp32 time", "x", "lower")
    bench.note(f"{args.threads} threads")
    for rep in bench.repetitions():
        ms = interleave(calls, rep)
        for key, *_ in LAYERS:
            bench.add(f"{key}_fp32_ms", ms[f"{key}_fp32"])
            bench.add(f"{key}_int8_ms", ms[f"{key}_int8"])
            bench.add(f"{key}_int8_over_fp32", ms[f"{key}_int8"] / ms[f"{key}_fp32"])
    bench.finish()


CASES = (Case(bench_runtime), Case(bench_path0), Case(bench_blocked_skip), Case(bench_int8_layers))

if __name__ == "__main__":
    run_suite(CASES)
