"""Device cost models: the shipped fits against their calibration figures, then the host:
3 repetitions of: calibrate with onnxruntime (stage graphs at 224x224, 224x320, 192x640), predict
random default-space candidates that were not in the sweep at those three sizes, and compare with
measurement.

    .venv/bin/python benchmarks/bench_devices.py [--candidates 8] [--scale 1] [--skip-host] [--data ../shared/data]
        [--reps 3] [--rounds 1] [--save DIR]     # also keep each repetition's probe results and held-out timings in DIR
    .venv/bin/python benchmarks/bench_devices.py --refit DIR   # the fit again on those, no measuring
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from explorer.cost import candidate_cost, get_device, profile_reference
from explorer.calibration.calibrate import calibrate, fit_results
from explorer.cost.fit import (PAPER_RPI4_TABLE2, PAPER_TX2_PATHS_MS, TX2_REFERENCES, Observation, errors,
                               kernel_workloads, rpi4_table2)
from explorer.calibration.measure import CandidateTimer
from explorer.calibration.peak import host_peak
from explorer.probe import read_results
from explorer.model import build_network
from explorer.model.reference import REFERENCES
from explorer.space import SearchSpace, paper_candidate

from _steady import speedometer as _speedometer, steadily


def shipped(data: Path) -> None:
    csv = data / "tx2-tvm-kernels" / "kernels.csv"
    for target, name in (("gpu", "tx2"), ("cpu", "tx2-cpu")):
        prof = get_device(name)
        obs = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(csv, target)]
        err = errors(prof, obs)["error"].abs()
        print(f"{name}: {len(obs)} measured kernels, median |error| {err.median():.1%} (target <= 20%), "
              f"within 10%: {(err <= 0.1).mean():.0%}")
    tx2 = get_device("tx2")
    ms = candidate_cost(paper_candidate(), paper_graph=True).path_latency_ms(tx2)[1:]   # the paper's graph
    for i, (got, want) in enumerate(zip(ms, PAPER_TX2_PATHS_MS), start=1):
        print(f"tx2 paper design path {i}: {got:.2f} ms vs {want} ms ({got / want - 1:+.1%}, target within 10%)")
    for name in TX2_REFERENCES:
        paper = REFERENCES[name].paper
        got = profile_reference(name, paper.input_size, tx2)["latency_ms"][0]
        print(f"tx2 {name} at {paper.input_size[0]}x{paper.input_size[1]}: {got:.2f} ms vs {paper.latency_ms} ms "
              f"({got / paper.latency_ms - 1:+.1%}, target within 15%)")
    for row in tx2.provenance.get("not_fitted", []):
        print(f"tx2 not fitted: {row}")
    print(f"tx2 energy: {tx2.energy_j(6.37):.3f} J at 6.37 ms (paper 0.2 J), {tx2.energy_j(554.7):.3f} J at 554.7 ms (paper 6.244 J)")
    for spec, got in rpi4_table2(get_device("rpi4")).items():
        print(f"rpi4 {spec}: {got:.3f} vs Table 2 {PAPER_RPI4_TABLE2[spec]} ({got - PAPER_RPI4_TABLE2[spec]:+.3f}, target within 0.03)")
    for c in get_device("rpi4").provenance["checks"]:
        if "target_ms" in c:
            print(f"rpi4 check {c['what']}: {c['predicted_ms']} ms vs {c['target_ms']} ms")


HOST_SIZES = ((224, 224), (224, 320), (192, 640))


def _sentinel() -> "callable":
    """Times one fixed graph (the paper design at 224x224, whole): the machine's speed at that moment."""
    from explorer.calibration.measure import session, time_call
    from explorer.model import build_network
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
        if held.get("int8_timings") and prof.int8 is not None:   # saved since stop 37, at HOST_SIZES[0]
            size_key = f"{HOST_SIZES[0][0]}x{HOST_SIZES[0][1]}"
            errs = np.array(errors(prof.int8, _int8_observations(cands, HOST_SIZES[0], held["int8_timings"]))["error"])
            a = np.abs(errs)
            medians.setdefault(f"int8 {size_key}", []).append(float(np.median(a)))
            print(f"  int8 {size_key}: {len(a)} deployed stage graphs, median |error| {np.median(a):.1%}, "
                  f"median signed {np.median(errs):+.1%}, within 10%: {(a <= 0.1).mean():.0%}")
    for size_key, ms in medians.items():
        print(f"refit {size_key}: {' '.join(f'{x:.1%}' for x in ms)} -> median {np.median(ms):.1%}")


def _int8_observations(cands, size, timings: dict) -> list:
    """``Observation``s of held-out int8 stage graphs from {candidate key: {graph name: ms}}."""
    obs = []
    for c in cands:
        cost = candidate_cost(c, size)
        obs += [Observation(f"{c.key}/{name}", [w for w in cost.workloads if w.stage in name.split("+")], ms, stages=1)
                for name, ms in timings.get(c.key, {}).items()]
    return obs


def _int8_timings(cands, size, slowness, rounds: int) -> dict:
    """The held-out candidates' deployed stage graphs, each quantized whole (as ``explorer export
    --quantize int8 --int8-stages all`` does), handing each other uint8 tensors, timed as the probe
    times them (in one chain, in sequence, under ``steadily``'s rule) in ``rounds`` interleaved rounds
    over the candidates: {candidate key: {graph name: median ms over the rounds}}."""
    from explorer.calibration.bundle import _int8_graphs
    from explorer.probe import WARMUP, chain_runs, chain_sessions, time_chain
    from explorer.model.onnx import example_inputs
    chains = {}
    for c in cands:
        graphs = _int8_graphs(build_network(c), size)
        chains[c.key] = ([name for name, _ in graphs],
                         chain_runs(chain_sessions([model for _, model in graphs]),
                                    {k: v.numpy() for k, v in example_inputs(size).items()}))
    taken: dict = {key: [] for key in chains}
    for _ in range(rounds):
        for key, (_, (runs, new_round)) in chains.items():
            ms, _, _ = _measure_steadily(lambda: time_chain(runs, WARMUP, 20, new_round=new_round), slowness, _fastest)
            taken[key].append(ms)
    return {key: dict(zip(chains[key][0], _per_path_median(r))) for key, r in taken.items()}


def host(n: int, seed: int, scale: float, reps: int = 3, save: Path | None = None, rounds: int = 1) -> None:
    """Each repetition is what a user does: calibrate (stage graphs at every size of ``STAGE_SIZES``),
    then measure ``n`` held-out candidates at each of ``HOST_SIZES``, and report the median per-path
    error of each size. A fixed graph timed before and after each step shows whether the machine
    itself changed speed in between (a shared machine does, by up to 4x here). Held-out candidates are
    measured under the rule the probe follows, against the speed the calibration measured at
    (``_measure_steadily``: a profile describes the machine undisturbed, and a held-out timing taken
    while another load slows it says nothing about the profile), every candidate at every size in
    ``rounds`` interleaved rounds, each path keeping its median over them: a spell of another load,
    or a drift of the machine's speed, then touches no one size or candidate alone."""
    cands = SearchSpace.from_yaml("anytime_depth").random_candidates(n, seed + 1)
    peak = host_peak()
    print(f"\nthis machine's peak: {peak.describe()}")
    sentinel = _sentinel()
    medians: dict = {size: [] for size in HOST_SIZES}
    int8_medians: list[float] = []
    for rep in range(1, reps + 1):
        speed = [sentinel()]
        t0 = time.perf_counter()
        tmp = tempfile.TemporaryDirectory(prefix="bench-devices-")   # the bundle: its speed checks, timed again
        results_out = save / f"rep{rep}-results.json" if save else Path(tmp.name) / "results.json"
        prof = calibrate(seed=seed + rep - 1, scale=scale, exclude={c.key for c in cands},   # held out: never in the sweep
                         results_out=results_out, bundle_out=Path(tmp.name) / "bundle")
        slowness = _speedometer(Path(tmp.name) / "bundle", read_results(results_out))
        held = {"candidates": [c.to_dict() for c in cands], "rounds": rounds, "timings": {}}
        speed.append(sentinel())
        print(f"rep {rep}: host calibration (scale {scale}, seed {seed + rep - 1}): {time.perf_counter() - t0:.0f} s; "
              f"{prof.provenance['conditions']['threads']} threads, onnxruntime {prof.provenance['conditions']['onnxruntime']}; "
              f"body exponent {prof.body_exponent:g}, compute and memory {'overlap' if prof.overlap else 'add'}; "
              f"speed checks varied by {prof.provenance['conditions'].get('speed_drift', float('nan')):.0%}, "
              f"{prof.provenance['conditions'].get('speed_remeasured', 0)} graphs timed again, "
              f"{prof.provenance['conditions'].get('retimed_outliers', 0)} more far above the fit")
        for fit in prof.provenance["fit"]:
            print(f"  fit on {fit['what']}: median |error| {fit['median_abs_error']:.1%}")
        timers = {(c.key, size): CandidateTimer(net, size) for c, net in ((c, build_network(c)) for c in cands)
                  for size in HOST_SIZES}
        taken: dict = {key: [] for key in timers}   # per round: (path ms, whole graph ms)
        timed_again = {size: 0 for size in HOST_SIZES}
        still_slow = {size: 0 for size in HOST_SIZES}
        for _ in range(rounds):
            for size in HOST_SIZES:
                for c in cands:
                    def measure(timer=timers[c.key, size]):
                        m = timer.measure(repeats=20)
                        return m.path_ms + [m.whole_ms]
                    ms, again, slow = _measure_steadily(measure, slowness, _fastest)
                    timed_again[size] += again
                    still_slow[size] += slow
                    taken[c.key, size].append((ms[:-1], ms[-1]))
        del timers
        for size in HOST_SIZES:
            key = f"{size[0]}x{size[1]}"
            held["timings"][key] = timings = {c.key: _per_path_median([p for p, _ in taken[c.key, size]]) for c in cands}
            errs = _size_errors(prof, cands, size, timings)
            a = np.abs(errs)
            medians[size].append(float(np.median(a)))
            per_round = [np.median(np.abs(_size_errors(prof, cands, size, {c.key: taken[c.key, size][r][0] for c in cands})))
                         for r in range(rounds)] if rounds > 1 else []
            fractions = [peak.fraction(candidate_cost(c, size).path_params_macs()[-1][1],
                                       float(np.median([w for _, w in taken[c.key, size]]))) for c in cands]
            print(f"  rep {rep} {key}: {n} held-out candidates, {len(a)} paths"
                  + (f", median over {rounds} rounds" if rounds > 1 else "") + ": median "
                  f"|error| {np.median(a):.1%}, within 10%: {(a <= 0.1).mean():.0%}, median signed {np.median(errs):+.1%}"
                  + (f" (each round alone: {' / '.join(f'{x:.1%}' for x in per_round)})" if rounds > 1 else "")
                  + f"; whole graphs at "
                  f"{' '.join(f'{f:.0%}' for f in fractions)} of fp32 peak; {timed_again[size]} taken again after the "
                  f"machine ran slow, {still_slow[size]} of {n * rounds} measurements still slow after it")
        if prof.int8 is not None:
            held["int8_timings"] = _int8_timings(cands, HOST_SIZES[0], slowness, rounds)
            errs = np.array(errors(prof.int8, _int8_observations(cands, HOST_SIZES[0], held["int8_timings"]))["error"])
            int8_medians.append(float(np.median(np.abs(errs))))
            print(f"  rep {rep} int8 at {HOST_SIZES[0][0]}x{HOST_SIZES[0][1]}: {len(errs)} deployed stage graphs of the "
                  f"held-out candidates, each quantized whole, timed in sequence"
                  + (f", median over {rounds} rounds" if rounds > 1 else "") + ": median "
                  f"|error| {np.median(np.abs(errs)):.1%}, within 10%: {(np.abs(errs) <= 0.1).mean():.0%}, median signed "
                  f"{np.median(errs):+.1%}")
        if save:
            (save / f"rep{rep}-heldout.json").write_text(json.dumps(held))
        tmp.cleanup()
        speed.append(sentinel())
        print(f"  machine speed (paper design whole graph at 224x224): {speed[0]:.2f} ms before calibrating, "
              f"{speed[1]:.2f} after, {speed[2]:.2f} after the held-out measurement "
              f"({max(speed) / min(speed) - 1:+.0%} between the slowest and fastest)")
    for size, ms in medians.items():
        print(f"host {size[0]}x{size[1]}: median per-path |error| over {reps} repetitions "
              f"{' '.join(f'{x:.1%}' for x in ms)} -> median {np.median(ms):.1%} (target <= 5%)")
    if int8_medians:
        print(f"host int8 {HOST_SIZES[0][0]}x{HOST_SIZES[0][1]}: median per-graph |error| over {reps} repetitions "
              f"{' '.join(f'{x:.1%}' for x in int8_medians)} -> median {np.median(int8_medians):.1%}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    ap.add_argument("--candidates", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", type=float, default=1.0, help="calibration sweep size (1 = explorer calibrate's)")
    ap.add_argument("--skip-host", action="store_true", help="only the shipped profiles")
    ap.add_argument("--reps", type=int, default=3, help="calibrations, each with its held-out measurement")
    ap.add_argument("--rounds", type=int, default=1,
                    help="interleaved rounds of the held-out measurement (each path keeps its median); each "
                         "measurement waits for a calm machine, so on a machine slow most of the time this "
                         "multiplies the waiting")
    ap.add_argument("--save", type=Path, help="keep each repetition's probe results and held-out timings here")
    ap.add_argument("--refit", type=Path, help="no measuring: fit --save's results again and compare")
    args = ap.parse_args()
    if args.refit:
        refit(args.refit)
        raise SystemExit(0)
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    if Path(args.data).is_dir():
        shipped(Path(args.data))
    if not args.skip_host:
        host(args.candidates, args.seed, args.scale, reps=args.reps, save=args.save, rounds=args.rounds)
