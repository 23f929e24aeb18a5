"""The probe bundle on this machine: bundle size (target <= 50 MB), the probe's run time (target
<= 3 min), and a profile fitted from a probe run against one from ``explorer calibrate`` run directly
(median per-path prediction difference over the held-out candidates of bench_devices.py, target
<= 5%). The probe is how a device without the package gets a profile; it must be small, quick, and
give the profile a direct calibration would.

    python benchmarks/bench_probe.py [--reps 3] [--candidates 24] [--seed 0]

Each repetition runs both calibrations, in an order that rotates; from the second on, the direct
calibration is also compared with the previous repetition's (the noise floor).
"""

import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from explorer.calibration.bundle import write_bundle
from explorer.calibration.calibrate import calibrate, fit_results, read_results
from explorer.cost import candidate_cost
from explorer.space import SearchSpace

from harness import Bench, interleave


def held_out(n: int, seed: int) -> list:
    # the same draw as bench_devices.py
    return SearchSpace.from_yaml("anytime_depth").random_candidates(n, seed + 1)


def probe_profile(tmp: Path, seed: int, exclude: set[str]) -> tuple[object, dict, float, float, float]:
    """(profile, results, bundle MB, bundle seconds, probe seconds) of a bundle run as a device runs it."""
    tar = tmp / "probe.tar"
    t0 = time.perf_counter()
    write_bundle(tar, seed=seed, exclude=exclude)
    t_bundle = time.perf_counter() - t0
    device = tmp / "device"
    device.mkdir()
    with tarfile.open(tar) as t:
        t.extractall(device)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "probe.pyz", "--out", "results.json"], cwd=device, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_probe = time.perf_counter() - t0
    res = read_results(device / "results.json")
    return fit_results(res, "probe"), res, tar.stat().st_size / 1e6, t_bundle, t_probe


def direct_profile(tmp: Path, seed: int, exclude: set[str]) -> tuple[object, dict, float]:
    """(profile, results, seconds) of ``explorer calibrate`` run in this process."""
    t0 = time.perf_counter()
    prof = calibrate(seed=seed, exclude=exclude, results_out=tmp / "direct.json")
    return prof, read_results(tmp / "direct.json"), time.perf_counter() - t0


def raw_difference(a: dict, b: dict) -> float:
    """Median |a/b - 1| over the graphs both runs timed (layers by id, stages by candidate/stage)."""
    d = [a["layers"][k] / b["layers"][k] - 1 for k in a["layers"] if k in b["layers"]]
    d += [ms / b["stages"][c][s] - 1 for c, st in a["stages"].items() for s, ms in st.items()
          if s in b["stages"].get(c, {})]
    return float(np.median(np.abs(d)))


def path_difference(costs: list, p: object, q: object) -> float:
    d = []
    for cost in costs:
        a, b = cost.path_latency_ms(p)[1:], cost.path_latency_ms(q)[1:]
        d += [x / y - 1 for x, y in zip(a, b)]
    return float(np.median(np.abs(d)))


if __name__ == "__main__":
    bench = Bench(__file__, "Probe bundle: size, run time, and agreement with a direct calibration", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = bench.parse_args(ap)
    cands = held_out(args.candidates, args.seed)
    keys = {c.key for c in cands}
    costs = [candidate_cost(c) for c in cands]
    for name, label, unit, better in (
            ("bundle_mb", "bundle size", "MB", "lower"), ("bundle_s", "bundle export", "s", "lower"),
            ("probe_s", "probe run", "s", "lower"), ("calibrate_s", "explorer calibrate", "s", "lower"),
            ("probe_vs_calibrate", "probe against calibrate: median per-path |difference|", "", "lower"),
            ("raw_difference", "probe against calibrate: median |difference| of raw graph timings", "", "lower"),
            ("calibrate_vs_previous", "calibrate against the previous repetition's (noise floor)", "", "lower")):
        bench.figure(name, label, unit, better)
    bench.note(f"{len(cands)} held-out candidates (seed {args.seed})")
    previous = None
    for rep in bench.repetitions():
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "p").mkdir()
            (Path(tmp) / "d").mkdir()
            got = interleave({"probe": lambda: probe_profile(Path(tmp) / "p", args.seed, keys),
                              "direct": lambda: direct_profile(Path(tmp) / "d", args.seed, keys)}, rep)
        via_probe, res, mb, t_bundle, t_probe = got["probe"]
        direct, direct_res, t_direct = got["direct"]
        for name, value in (("bundle_mb", mb), ("bundle_s", t_bundle), ("probe_s", t_probe), ("calibrate_s", t_direct),
                            ("probe_vs_calibrate", path_difference(costs, via_probe, direct)),
                            ("raw_difference", raw_difference(res, direct_res))):
            bench.add(name, value)
        if previous is not None:
            bench.add("calibrate_vs_previous", path_difference(costs, direct, previous))
        previous = direct
    bench.finish()
