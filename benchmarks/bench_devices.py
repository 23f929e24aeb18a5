"""Device cost models: the shipped fits against the figures they were fitted to, then this host: each
repetition calibrates with onnxruntime (stage graphs at 224x224, 224x320, 192x640), predicts random
default-space candidates that were not in the calibration's sweep at those three sizes, and compares
with measurement. A study ranks candidates by these predictions, so their per-path error on unseen
candidates is what the cost model is judged by.

    python benchmarks/bench_devices.py [--reps 3] [--candidates 8] [--scale 1] [--skip-host] [--data DIR]
        [--rounds 1] [--save DIR]     # also keep each repetition's probe results and held-out timings in DIR
    python benchmarks/bench_devices.py --refit DIR   # the fit again on those, no measuring (prints, no record)

Held-out candidates are measured under the rule the probe follows (``_steady.steadily``: taken again
while the machine runs slower than during the calibration), every candidate at every size in
--rounds rounds whose order rotates, each path keeping its median over them. A fixed graph timed
before and after each step shows whether the machine itself changed speed in between.
"""

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from explorer.calibration.calibrate import calibrate, fit_results
from explorer.calibration.measure import CandidateTimer
from explorer.calibration.peak import host_peak
from explorer.cost import candidate_cost, get_device, profile_reference
from explorer.cost.fit import (PAPER_RPI4_TABLE2, PAPER_TX2_PATHS_MS, TX2_REFERENCES, Observation, errors,
                               kernel_workloads, rpi4_table2)
from explorer.model import build_network
from explorer.model.reference import REFERENCES
from explorer.probe import read_results
from explorer.space import SearchSpace, paper_candidate

from _steady import speedometer, steadily
from harness import Bench, rotated

HOST_SIZES = ((224, 224), (224, 320), (192, 640))


def _key(size) -> str:
    return f"{size[0]}x{size[1]}"


def shipped(bench: Bench, data: Path) -> None:
    """The shipped tx2 and rpi4 profiles against their own calibration figures (one value each)."""
    csv = data / "tx2-tvm-kernels" / "kernels.csv"
    for target, name in (("gpu", "tx2"), ("cpu", "tx2-cpu")):
        prof = get_device(name)
        obs = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(csv, target)]
        err = errors(prof, obs)["error"].abs()
        bench.add(bench.figure(f"shipped_{name}_kernel_error", f"shipped {name}: median |error| over measured kernels",
                               "", "lower"), err.median())
        print(f"{name}: {len(obs)} measured kernels, median |error| {err.median():.1%} (target <= 20%), "
              f"within 10%: {(err <= 0.1).mean():.0%}")
    tx2 = get_device("tx2")
    ms = candidate_cost(paper_candidate(), paper_graph=True).path_latency_ms(tx2)[1:]   # the paper's graph
    worst = max(abs(got / want - 1) for got, want in zip(ms, PAPER_TX2_PATHS_MS))
    bench.add(bench.figure("shipped_tx2_paper_paths_error", "shipped tx2: largest |error| on the paper's path times",
                           "", "lower"), worst)
    for i, (got, want) in enumerate(zip(ms, PAPER_TX2_PATHS_MS), start=1):
        print(f"tx2 paper design path {i}: {got:.2f} ms vs {want} ms ({got / want - 1:+.1%}, target within 10%)")
    for name in TX2_REFERENCES:
        paper = REFERENCES[name].paper
        got = profile_reference(name, paper.input_size, tx2)["latency_ms"][0]
        print(f"tx2 {name} at {paper.input_size[0]}x{paper.input_size[1]}: {got:.2f} ms vs {paper.latency_ms} ms "
              f"({got / paper.latency_ms - 1:+.1%}, target within 15%)")
    for row in tx2.provenance.get("not_fitted", []):
        print(f"tx2 not fitted: {row}")
    print(f"tx2 energy: {tx2.energy_j(6.37):.3f} J at 6.37 ms (paper 0.2 J), {tx2.energy_j(554.7):.3f} J at "
          "554.7 ms (paper 6.244 J)")
    for spec, got in rpi4_table2(get_device("rpi4")).items():
        print(f"rpi4 {spec}: {got:.3f} vs Table 2 {PAPER_RPI4_TABLE2[spec]} ({got - PAPER_RPI4_TABLE2[spec]:+.3f}, "
              "target within 0.03)")
    for c in get_device("rpi4").provenance["checks"]:
        if "target_ms" in c:
            print(f"rpi4 check {c['what']}: {c['predicted_ms']} ms vs {c['target_ms']} ms")


def _sentinel():
    """Times one fixed graph (the paper design at 224x224, whole): the machine's speed at that moment."""
    from explorer.calibration.measure import session, time_call
    from explorer.model.onnx import example_inputs, export_whole
    sess = session(export_whole(build_network(paper_candidate()), (224, 224)))
    feeds = {k: v.numpy() for k, v in example_inputs((224, 224)).items()}
    return lambda: time_call(lambda: sess.run(None, feeds), 3, 15)


def _measure_steadily(measure, slowness, combine) -> tuple:
    """``measure()`` under the probe's rule, against the calibration's own speed (``_steady.steadily``:
    taken again while the machine ran slow, ``combine`` folding each new result into the kept one).
    Returns the kept result, how many times it was taken again, and whether the machine still ran
    slow at the end (``Steady.slowness`` above ``1 + SLOW``)."""
    got = steadily(measure, slowness, combine)
    return got.result, got.again, bool(got.note())


def _fastest(kept: list[float], new: list[float]) -> list[float]:
    """Per path (or graph), the faster of two timings: the probe keeps a graph's faster timing too."""
    return [min(a, b) for a, b in zip(kept, new)]


def _per_path_median(rounds: list[list[float]]) -> list[float]:
    """Per path (or graph), its median timing over the rounds."""
    return [float(np.median(t)) for t in zip(*rounds)]


def _size_errors(prof, cands, size, timings: dict) -> list[float]:
    """Signed per-path errors of ``prof`` against held-out timings {candidate key: path ms}."""
    errs = []
    for c in cands:
        pred = candidate_cost(c, size).path_latency_ms(prof)
        errs += [p / q - 1 for p, q in zip(pred[1:], timings[c.key][1:])]
    return errs


def _int8_observations(cands, size, timings: dict) -> list:
    """``Observation``s of held-out int8 stage graphs from {candidate key: {graph name: ms}}."""
    obs = []
    for c in cands:
        cost = candidate_cost(c, size)
        obs += [Observation(f"{c.key}/{name}", [w for w in cost.workloads if w.stage in name.split("+")], ms, stages=1)
                for name, ms in timings.get(c.key, {}).items()]
    return obs


def refit(folder: Path) -> None:
    """Fits each saved repetition's probe results again (the code as it is now) and compares with the
    held-out timings saved beside them: a change to the fit judged on the very same measurements."""
    from explorer.space import Candidate
    medians: dict = {}
    for rep_file in sorted(folder.glob("rep*-heldout.json")):
        held = json.loads(rep_file.read_text())
        prof = fit_results(read_results(folder / rep_file.name.replace("-heldout", "-results")))
        cands = [Candidate.from_dict(d) for d in held["candidates"]]
        print(f"{rep_file.stem}: body exponent {prof.body_exponent:g}, "
              f"{'overlap' if prof.overlap else 'add'}; fit " + "; ".join(
                  f"{f['what']}: {f['median_abs_error']:.1%}" for f in prof.provenance["fit"]))
        for size_key, timings in held["timings"].items():
            size = tuple(int(x) for x in size_key.split("x"))
            errs = _size_errors(prof, cands, size, timings)
            a = np.abs(errs)
            medians.setdefault(size_key, []).append(float(np.median(a)))
            print(f"  {size_key}: median |error| {np.median(a):.1%}, median signed {np.median(errs):+.1%}, "
                  f"within 10%: {(a <= 0.1).mean():.0%}")
        if held.get("int8_timings") and prof.int8 is not None:   # int8 held-out timings, at HOST_SIZES[0]
            size_key = _key(HOST_SIZES[0])
            errs = np.array(errors(prof.int8, _int8_observations(cands, HOST_SIZES[0], held["int8_timings"]))["error"])
            a = np.abs(errs)
            medians.setdefault(f"int8 {size_key}", []).append(float(np.median(a)))
            print(f"  int8 {size_key}: {len(a)} deployed stage graphs, median |error| {np.median(a):.1%}, "
                  f"median signed {np.median(errs):+.1%}, within 10%: {(a <= 0.1).mean():.0%}")
    for size_key, ms in medians.items():
        print(f"refit {size_key}: {' '.join(f'{x:.1%}' for x in ms)} -> median {np.median(ms):.1%}")


def _int8_timings(cands, size, slowness, rounds: int) -> dict:
    """The held-out candidates' deployed stage graphs, each quantized whole (as ``explorer export
    --quantize int8 --int8-stages all`` does), handing each other uint8 tensors, timed as the probe
    times them (in one chain, in sequence, under ``steadily``'s rule) in ``rounds`` rounds over the
    candidates in rotating order: {candidate key: {graph name: median ms over the rounds}}."""
    from explorer.calibration.bundle import _int8_graphs
    from explorer.model.onnx import example_inputs
    from explorer.probe import WARMUP, chain_runs, chain_sessions, time_chain
    chains = {}
    for c in cands:
        graphs = _int8_graphs(build_network(c), size)
        chains[c.key] = ([name for name, _ in graphs],
                         chain_runs(chain_sessions([model for _, model in graphs]),
                                    {k: v.numpy() for k, v in example_inputs(size).items()}))
    taken: dict = {key: [] for key in chains}
    for r in range(rounds):
        for key in rotated(list(chains), r):
            runs, new_round = chains[key][1]
            ms, _, _ = _measure_steadily(lambda: time_chain(runs, WARMUP, 20, new_round=new_round), slowness, _fastest)
            taken[key].append(ms)
    return {key: dict(zip(chains[key][0], _per_path_median(r))) for key, r in taken.items()}


def _held_out_timings(cands, slowness, rounds: int) -> tuple[dict, dict, dict]:
    """Every candidate at every size, ``rounds`` rounds in rotating order, under the probe's rule:
    ({(key, size): [(path ms, whole ms) per round]}, {size: times taken again}, {size: still slow})."""
    timers = {(c.key, size): CandidateTimer(build_network(c), size) for c in cands for size in HOST_SIZES}
    taken: dict = {key: [] for key in timers}
    again_by_size = {size: 0 for size in HOST_SIZES}
    slow_by_size = {size: 0 for size in HOST_SIZES}
    for r in range(rounds):
        for key in rotated(list(timers), r):
            def measure(timer=timers[key]):
                m = timer.measure(repeats=20)
                return m.path_ms + [m.whole_ms]
            ms, again, slow = _measure_steadily(measure, slowness, _fastest)
            again_by_size[key[1]] += again
            slow_by_size[key[1]] += slow
            taken[key].append((ms[:-1], ms[-1]))
    return taken, again_by_size, slow_by_size


def declare(bench: Bench) -> None:
    bench.figure("calibration_s", "host calibration time", "s", "lower")
    for size in HOST_SIZES:
        k = _key(size)
        bench.figure(f"host_{k}_median_error", f"host {k}: median per-path |error| on held-out candidates", "",
                     "lower")
        bench.figure(f"host_{k}_within_10pct", f"host {k}: share of paths within 10%", "", "higher")
        bench.figure(f"host_{k}_median_signed", f"host {k}: median signed error", "", None)
        bench.figure(f"host_{k}_peak_fraction", f"host {k}: whole graphs' median share of fp32 peak", "", "higher")
    bench.figure("host_int8_median_error", f"host int8 {_key(HOST_SIZES[0])}: median per-graph |error|", "", "lower")
    bench.figure("machine_speed_change", "machine speed change over the repetition (slowest / fastest - 1)", "",
                 "lower")


def _report_size(bench: Bench, prof, cands, size, taken: dict, peak, rounds: int) -> dict:
    """Adds one size's figures; returns its held-out timings {candidate key: per-path median ms}."""
    k = _key(size)
    timings = {c.key: _per_path_median([p for p, _ in taken[c.key, size]]) for c in cands}
    errs = _size_errors(prof, cands, size, timings)
    a = np.abs(errs)
    fractions = [peak.fraction(candidate_cost(c, size).path_params_macs()[-1][1],
                               float(np.median([w for _, w in taken[c.key, size]]))) for c in cands]
    bench.add(f"host_{k}_median_error", np.median(a))
    bench.add(f"host_{k}_within_10pct", (a <= 0.1).mean())
    bench.add(f"host_{k}_median_signed", np.median(errs))
    bench.add(f"host_{k}_peak_fraction", np.median(fractions))
    if rounds > 1:
        per_round = [np.median(np.abs(_size_errors(prof, cands, size,
                                                   {c.key: taken[c.key, size][r][0] for c in cands})))
                     for r in range(rounds)]
        print(f"  {k}: each round alone: {' / '.join(f'{x:.1%}' for x in per_round)}")
    return timings


def host_rep(bench: Bench, rep: int, cands, args, sentinel, peak) -> None:
    """One repetition, what a user does: calibrate (excluding the held-out candidates), then measure the
    held-out candidates at each of ``HOST_SIZES`` and compare with the profile's predictions."""
    speed = [sentinel()]
    t0 = time.perf_counter()
    tmp = tempfile.TemporaryDirectory(prefix="bench-devices-")   # the bundle: its speed checks, timed again
    results_out = args.save / f"rep{rep + 1}-results.json" if args.save else Path(tmp.name) / "results.json"
    prof = calibrate(seed=args.seed + rep, scale=args.scale, exclude={c.key for c in cands},   # held out
                     results_out=results_out, bundle_out=Path(tmp.name) / "bundle")
    bench.add("calibration_s", time.perf_counter() - t0)
    slowness = speedometer(Path(tmp.name) / "bundle", read_results(results_out))
    speed.append(sentinel())
    cond = prof.provenance["conditions"]
    print(f"  calibration (scale {args.scale}, seed {args.seed + rep}): {cond['threads']} threads, onnxruntime "
          f"{cond['onnxruntime']}; body exponent {prof.body_exponent:g}, compute and memory "
          f"{'overlap' if prof.overlap else 'add'}; speed checks varied by "
          f"{cond.get('speed_drift', float('nan')):.0%}, "
          f"{cond.get('speed_remeasured', 0)} graphs timed again; fit " + "; ".join(
              f"{f['what']}: {f['median_abs_error']:.1%}" for f in prof.provenance["fit"]), flush=True)
    taken, again, slow = _held_out_timings(cands, slowness, args.rounds)
    held = {"candidates": [c.to_dict() for c in cands], "rounds": args.rounds, "timings": {}}
    for size in HOST_SIZES:
        held["timings"][_key(size)] = _report_size(bench, prof, cands, size, taken, peak, args.rounds)
        print(f"  {_key(size)}: {again[size]} measurements taken again after the machine ran slow, "
              f"{slow[size]} of {len(cands) * args.rounds} still slow after it")
    if prof.int8 is not None:
        held["int8_timings"] = _int8_timings(cands, HOST_SIZES[0], slowness, args.rounds)
        errs = np.array(errors(prof.int8, _int8_observations(cands, HOST_SIZES[0], held["int8_timings"]))["error"])
        bench.add("host_int8_median_error", np.median(np.abs(errs)))
    if args.save:
        (args.save / f"rep{rep + 1}-heldout.json").write_text(json.dumps(held))
    tmp.cleanup()
    speed.append(sentinel())
    bench.add("machine_speed_change", max(speed) / min(speed) - 1)


if __name__ == "__main__":
    bench = Bench(__file__, "Cost models: shipped fits, and host calibration on held-out candidates", __doc__)
    ap = bench.parser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    ap.add_argument("--candidates", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0, help="calibration sweep size (1 = explorer calibrate's)")
    ap.add_argument("--skip-host", action="store_true", help="only the shipped profiles")
    ap.add_argument("--rounds", type=int, default=1,
                    help="rounds of the held-out measurement (each path keeps its median); each measurement "
                         "waits for a calm machine, so on a machine slow most of the time this multiplies the waiting")
    ap.add_argument("--save", type=Path, help="keep each repetition's probe results and held-out timings here")
    ap.add_argument("--refit", type=Path, help="no measuring: fit --save's results again and compare (no record)")
    args = bench.parse_args(ap)
    if args.refit:
        refit(args.refit)
        raise SystemExit(0)
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    if Path(args.data).is_dir():
        shipped(bench, Path(args.data))
    if not args.skip_host:
        cands = SearchSpace.from_yaml("anytime_depth").random_candidates(args.candidates, args.seed + 1)
        peak = host_peak()
        bench.note(f"this machine's peak: {peak.describe()}; {args.candidates} held-out candidates, scale "
                   f"{args.scale}, {args.rounds} rounds")
        declare(bench)
        sentinel = _sentinel()
        for rep in bench.repetitions():
            host_rep(bench, rep, cands, args, sentinel, peak)
    bench.finish()
