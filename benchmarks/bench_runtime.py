"""Deployment on this machine: staged execution against one whole graph, onnxruntime against PyTorch
eager, int8 against fp32 (speed and each path's RMSE; the export's own choice of int8 stages, the same
without the uint8 handoff between int8 stages, and every stage int8), and the path ready times and
anytime loss measured against what the host profile predicts. These are the deployment claims: staging
costs little over the whole graph, onnxruntime beats eager, int8 pays, and the profile predicts.

    python benchmarks/bench_runtime.py [--reps 5] [--frames 16] [--deadlines 40] [--train-steps 100]
        [--skip-int8] [--skip-anytime]

Each repetition times every variant in interleaved blocks whose order rotates, then (unless
--skip-anytime) the ready times and the anytime loss, taken at the speed the host calibration
measured at (``_steady.steadily``: taken again while the machine ran slow).
"""

import statistics
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from explorer.anytime import anytime_loss
from explorer.calibration.calibrate import calibrate, read_results
from explorer.calibration.measure import session
from explorer.calibration.peak import gemm_gmacs, host_peak
from explorer.cost import candidate_cost
from explorer.data import open_dataset
from explorer.deploy.export import Quantization, export_network
from explorer.deploy.runtime import AnytimeRunner, measured_anytime
from explorer.metrics import MetricAverager, depth_metrics
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.space import paper_candidate
from explorer.training.train import TrainConfig, train

from _steady import note_steadiness, speedometer, steadily
from harness import Bench, time_interleaved

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
    bench.note("int8 export's stages: " + "; ".join(f"{st['name']} {st['precision']}" for st in m["stages"]))
    for key, mm in (("int8", m), ("int8_all", m_all)):
        deg = mm["quantization"]["rmse_degradation"]
        bench.add(bench.figure(f"{key}_last_path_rmse_change", f"{INT8[key]}: last path RMSE change", "", "lower"),
                  deg[-1])
        bench.note(f"{INT8[key]}: RMSE change per path {' '.join(f'{100 * d:+.1f}%' for d in deg)} on "
                   f"{mm['quantization']['evaluation']['frames']} frames; handed over: "
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


if __name__ == "__main__":
    bench = Bench(__file__, "Deployment: staged against whole graph, onnxruntime against eager, int8, "
                            "profile predictions", __doc__, reps=5)
    ap = bench.parser()
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--deadlines", type=int, default=40)
    ap.add_argument("--train-steps", type=int, default=100)
    ap.add_argument("--skip-anytime", action="store_true", help="only the staged, eager and int8 timings")
    ap.add_argument("--skip-int8", action="store_true", help="no int8 export and timing")
    args = bench.parse_args(ap)
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
