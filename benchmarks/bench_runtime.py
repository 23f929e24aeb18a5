"""Deployment on this machine: staged execution against one whole graph, onnxruntime against
PyTorch eager, int8 against fp32 (speed and each path's RMSE; the export's own choice of int8 stages,
the same without the uint8 handoff between int8 stages, and every stage int8), and the measured anytime loss against
the one the host profile predicts.

    .venv/bin/python benchmarks/bench_runtime.py [--frames 16] [--deadlines 40]

What it compares is timed in interleaved blocks (``_timing.time_interleaved``): a shared machine that
changes speed every few seconds would otherwise give one variant its slow spell and another its calm.
The path ready times and the anytime loss are set against the host profile at the speed its
calibration measured at (``_steady.steadily``: taken again when the machine ran slow), as
bench_devices.py measures its held-out candidates.
"""

import argparse
from dataclasses import replace
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost
from explorer.calibration.calibrate import calibrate, read_results
from explorer.calibration.measure import session, time_call
from explorer.calibration.peak import gemm_gmacs, host_peak
from explorer.data import open_dataset
from explorer.deploy.export import Quantization, export_network
from explorer.metrics import MetricAverager, depth_metrics
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_whole
from explorer.deploy.runtime import AnytimeRunner, measured_anytime
from explorer.space import paper_candidate
from explorer.training.train import TrainConfig, train

from _steady import speedometer, steadily
from _timing import time_interleaved

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--deadlines", type=int, default=40)
    ap.add_argument("--train-steps", type=int, default=100)
    ap.add_argument("--skip-anytime", action="store_true", help="only the staged, eager and int8 timings")
    ap.add_argument("--skip-int8", action="store_true", help="no int8 export and timing")
    args = ap.parse_args()
    size = (224, 224)
    cand = paper_candidate()
    torch.manual_seed(0)
    net = build_network(cand)
    cfg = TrainConfig(steps=args.train_steps, batch_size=16, input_size=(64, 64))
    train(net, open_dataset("synthetic", "train", (64, 64)), open_dataset("synthetic:48:16", "val", (64, 64)), cfg,
          val_limit=16)
    net.eval()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        export_network(net, out, size)
        runner = AnytimeRunner(out)
        plain = AnytimeRunner(out, handoff=False)
        print("tensors handed between stages as onnxruntime holds them: "
              + (", ".join(f"{name} ({form})" for name, form in runner.handed_off.items()) or "none"))
        env = {k: v.numpy() for k, v in example_inputs(size).items()}
        staged, with_deadline, plain_staged, bare_staged, whole_ms = [], [], [], [], []
        whole = session(export_whole(net, size))
        feeds = {"image": env["image"], "scan": env["scan"]}

        def bare_chain():  # the stage sessions alone: no input checks, deadline timer or halting
            values = dict(feeds)
            for _, sess, ins, outs in runner.sessions:
                values.update(zip(outs, sess.run(outs, {n: values[n] for n in ins})))

        shared_only, own_only = AnytimeRunner(out, arenas="shared"), AnytimeRunner(out, arenas="own")

        shared_staged, own_staged = [], []
        img, scan = torch.from_numpy(env["image"]), torch.from_numpy(env["scan"])
        eager_ms = []
        image, scan_np = env["image"][0], env["scan"][0]

        def eager():
            with torch.no_grad():
                net(img, scan)

        series = {"staged": (staged, lambda: runner.run(image, scan_np)),
                  "with a deadline": (with_deadline, lambda: runner.run(image, scan_np, 1e4)),
                  "without the handoff": (plain_staged, lambda: plain.run(image, scan_np)),
                  "bare stage chain": (bare_staged, bare_chain),
                  "held to the shared arena": (shared_staged, lambda: shared_only.run(image, scan_np)),
                  "held to arenas of their own": (own_staged, lambda: own_only.run(image, scan_np)),
                  "whole graph": (whole_ms, lambda: whole.run(None, feeds)),
                  "eager": (eager_ms, eager)}
        for rep in range(5):  # blocks of calls of each in turn, so that all of them see the same machine
            for name, ms in time_interleaved({k: fn for k, (_, fn) in series.items()}, blocks=5).items():
                series[name][0].append(ms)
            w = whole_ms[-1]
            print(f"  rep {rep + 1}: whole graph {w:.2f} ms; staged {staged[-1]:.2f} ms ({staged[-1] / w - 1:+.1%}), "
                  f"with a deadline {with_deadline[-1]:.2f} ({with_deadline[-1] / w - 1:+.1%}), without the "
                  f"handoff {plain_staged[-1]:.2f} ({plain_staged[-1] / w - 1:+.1%}), bare stage chain "
                  f"{bare_staged[-1]:.2f} ({bare_staged[-1] / w - 1:+.1%}), held to the shared arena "
                  f"{shared_staged[-1]:.2f} ({shared_staged[-1] / w - 1:+.1%}), held to arenas of their own "
                  f"{own_staged[-1]:.2f} ({own_staged[-1] / w - 1:+.1%}); PyTorch eager {eager_ms[-1]:.2f} ms, "
                  f"{eager_ms[-1] / w:.2f}x the whole graph")
        w = statistics.median(whole_ms)
        print(f"staged execution vs one whole graph ({w:.2f} ms), medians of 5: "
              + ", ".join(f"{label} {statistics.median(t):.2f} ms {statistics.median(t) / w - 1:+.1%}" for label, t in
                          (("staged", staged), ("with a deadline", with_deadline),
                           ("without the handoff", plain_staged), ("the stage sessions alone", bare_staged),
                           ("held to the shared arena", shared_staged), ("held to arenas of their own", own_staged)))
              + " (goal <= 5%)")
        print(f"the runner's runs per session set (shared arena, arenas of their own): {runner.arena_choice.runs}")
        eager = statistics.median(eager_ms)
        ratios = [e / w for e, w in zip(eager_ms, whole_ms)]
        peak = host_peak()
        macs = candidate_cost(cand, size).path_params_macs()[-1][1]
        print(f"this machine's peak: {peak.describe()}")
        print(f"whole graph: {macs / 1e9:.3f} GMAC in {w:.2f} ms = {macs / (w * 1e6):.1f} GMAC/s, "
              f"{peak.fraction(macs, w):.0%} of fp32 peak (goal >= 50%)")
        print(f"PyTorch eager {eager:.2f} ms ({torch.get_num_threads()} threads) vs onnxruntime whole graph {w:.2f} ms "
              f"(medians of 5): {statistics.median(ratios):.2f}x per rep ({min(ratios):.2f}-{max(ratios):.2f}; goal >= 3x)")
        gemm = gemm_gmacs()
        g = statistics.median(gemm)
        print(f"attainable here: a 1024^3 fp32 matrix product in onnxruntime, 5 reps: "
              f"{' '.join(f'{r:.1f}' for r in gemm)} GMAC/s, median {g:.1f} ({g / peak.fp32_gmacs:.0%} of nominal peak); "
              f"whole graph at {macs / (w * 1e6) / g:.0%} of it; 3x eager would need {3 * macs / (eager * 1e6):.1f} GMAC/s, "
              f"{3 * macs / (eager * 1e6) / g:.0%} of it")

        if not args.skip_int8:
            q8 = out / "int8"   # inside the temporary folder: removed with it
            m = export_network(net, q8, size, quantization=Quantization(data="synthetic", max_degradation=1.0))
            runner8 = AnytimeRunner(q8)
            print("int8 export, per stage graph (kept int8 where that saved the staged runtime at least 5% of the "
                  "stage's fp32 time here; the stage's own ms in the chain, then the chain's): "
                  + "; ".join(f"{st['name']} {st['precision']}" + (
                      f" ({st['ms_here']['int8']:.2f} vs {st['ms_here']['fp32']:.2f} ms; staged "
                      f"{st['ms_here']['staged_int8']:.2f} vs {st['ms_here']['staged_fp32']:.2f} ms)"
                      if "ms_here" in st else "") for st in m["stages"]))
            m_all = export_network(net, out / "int8-all", size,
                                   quantization=Quantization(data="synthetic", max_degradation=1.0, stages="all"))
            variants = {"fp32": runner, "int8": runner8, "int8, no uint8 handoff": AnytimeRunner(q8, handoff=False),
                        "int8 all stages": AnytimeRunner(out / "int8-all")}
            for label in ("int8", "int8 all stages"):
                print(f"{label}: tensors handed over: "
                      + (", ".join(f"{n} ({form})" for n, form in variants[label].handed_off.items()) or "none"))
            # PyTorch eager (fp32) in the same blocks: what a user deploying int8 gains over running the model
            calls = {**{k: (lambda r=r: r.run(image, scan_np)) for k, r in variants.items()},
                     "PyTorch eager": series["eager"][1]}
            times8: dict[str, list[float]] = {k: [] for k in calls}
            for rep in range(5):  # interleaved in blocks
                got = time_interleaved(calls, blocks=5)
                for k, ms in got.items():
                    times8[k].append(ms)
                print(f"  rep {rep + 1}: staged " + ", ".join(f"{k} {ms:.2f} ms" for k, ms in got.items())
                      + f"; int8 {got['fp32'] / got['int8']:.2f}x, "
                      f"all stages {got['fp32'] / got['int8 all stages']:.2f}x, "
                      f"int8 {got['PyTorch eager'] / got['int8']:.2f}x eager")
            f, i = statistics.median(times8["fp32"]), statistics.median(times8["int8"])
            print("medians of 5: " + ", ".join(f"{k} {statistics.median(t):.2f} ms ({f / statistics.median(t):.2f}x)"
                                               for k, t in times8.items()))
            for label, mm in (("int8", m), ("int8 all stages", m_all)):
                deg = mm["quantization"]["rmse_degradation"]
                print(f"{label}: RMSE change per path on {mm['quantization']['evaluation']['frames']} frames: "
                      f"{' '.join(f'{100 * d:+.1f}%' for d in deg)} (goal: last path within 2%)")
            print(f"int8 (static QDQ) vs fp32, staged, medians of 5: {i:.2f} vs {f:.2f} ms, {f / i:.2f}x "
                  "(goal >= 1.8x)")
            print(f"int8 staged: {macs / (i * 1e6):.1f} GMAC/s, {peak.fraction(macs, i, 'int8'):.0%} of int8 peak")
            vs_eager = [e / q for e, q in zip(times8["PyTorch eager"], times8["int8"])]
            print(f"int8 staged vs PyTorch eager (fp32), same blocks: {statistics.median(vs_eager):.2f}x per rep "
                  f"({min(vs_eager):.2f}-{max(vs_eager):.2f}; the 3x goal is fp32 against fp32, above)")

        if args.skip_anytime:
            raise SystemExit(0)
        # the profile, and the machine's speed during its calibration: what follows is timed at that speed
        # (``_steady.steadily``), as bench_devices.py times its held-out candidates
        prof = calibrate(results_out=out / "calibration.json", bundle_out=out / "calibration-bundle")
        slowness = speedometer(out / "calibration-bundle", read_results(out / "calibration.json"))
        pred_ms = candidate_cost(cand, size).path_latency_ms(prof)
        for label, r, c in (("fp32", runner, cand),) + ((("int8", runner8, replace(cand, precision="int8")),)
                                                          if not args.skip_int8 else ()):

            def ready_times(r=r) -> list[float]:   # each path's median ready time over 20 whole runs
                ready = [[] for _ in range(cand.num_paths)]
                for _ in range(20):
                    for path, ms in r.run(env["image"][0], env["scan"][0]).completed:
                        ready[path].append(ms)
                return [statistics.median(t) for t in ready]
            steady = [steadily(ready_times, slowness) for _ in range(3)]
            per_rep = [x.result for x in steady]
            predicted = candidate_cost(c, size).path_latency_ms(prof)
            errs = [[q / m - 1 if m else 0.0 for m, q in zip(rep_ms, predicted)] for rep_ms in per_rep]   # path 0: 0 ms
            print(f"{label} path ready times vs predicted by the host profile, 3 reps of 20 runs "
                  f"({sum(x.again for x in steady)} taken again after the machine ran slow"
                  f"{''.join(f'; rep {k + 1}{x.note()}' for k, x in enumerate(steady) if x.note())}): "
                  + ", ".join(f"path {p} {statistics.median(rm[p] for rm in per_rep):.2f} vs {predicted[p]:.2f} ms "
                              f"({statistics.median(e[p] for e in errs):+.1%}; reps "
                              f"{' '.join(f'{e[p]:+.1%}' for e in errs)})" for p in range(1, cand.num_paths)))
        ds = open_dataset("synthetic", "val", size, train_augment=False)
        frames = [ds[i] for i in range(args.frames)]
        per_path = [MetricAverager() for _ in range(cand.num_paths)]
        with torch.no_grad():
            for f in frames:
                outs = net(f["image"][None], f["scan"][None], f["scan_row"])
                for p, o in enumerate(outs):
                    per_path[p].add(depth_metrics(o[0, 0], f["depth"][0]))
        losses = [a.result()["rmse"] for a in per_path]
        b_max = 1.25 * pred_ms[-1]
        predicted = anytime_loss(pred_ms, losses, f"time:uniform:{b_max}ms")
        grid = (np.arange(args.deadlines) + 0.5) * b_max / args.deadlines
        print(f"predicted path times (host profile): {' '.join(f'{x:.2f}' for x in pred_ms[1:])} ms")
        steady = [steadily(lambda: measured_anytime(runner, frames, grid)["anytime_loss"], slowness) for _ in range(3)]
        losses = [x.result for x in steady]
        gaps = [x / predicted - 1 for x in losses]
        print(f"anytime loss U(0, {b_max:.1f} ms), measured vs predicted {predicted:.4f}, 3 reps "
              f"({sum(x.again for x in steady)} taken again after the machine ran slow): "
              f"{' '.join(f'{g:+.1%}{x.note()}' for g, x in zip(gaps, steady))}, median {statistics.median(gaps):+.1%} (goal within 5%)")
