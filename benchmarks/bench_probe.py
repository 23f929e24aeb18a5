"""The probe bundle on this machine: bundle size (target <= 50 MB), the probe's run time (target
<= 3 min), and a profile fitted from a probe run against one from `explorer calibrate` run directly
(median per-path prediction difference over the held-out candidates of bench_devices.py, target
<= 5%). Repeated --repeats times, the two calibrations interleaved; every repetition and the median.

    .venv/bin/python benchmarks/bench_probe.py [--repeats 3] [--candidates 24]
"""

import argparse
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from explorer.cost import candidate_cost
from explorer.calibration.bundle import write_bundle
from explorer.calibration.calibrate import calibrate, fit_results, read_results
from explorer.space import SearchSpace


def held_out(n: int, seed: int) -> list:
    # the same draw as bench_devices.py
    return SearchSpace.from_yaml("anytime_depth").random_candidates(n, seed + 1)


def probe_profile(tmp: Path, seed: int, exclude: set[str]) -> tuple[object, dict, float, float, float]:
    tar = tmp / "probe.tar"
    t0 = time.perf_counter()
    write_bundle(tar, seed=seed, exclude=exclude)
    t_bundle = time.perf_counter() - t0
    device = tmp / "device"
    device.mkdir()
    with tarfile.open(tar) as t:
        t.extractall(device)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "probe.py", "--out", "results.json"], cwd=device, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    t_probe = time.perf_counter() - t0
    res = read_results(device / "results.json")
    return fit_results(res, "probe"), res, tar.stat().st_size / 1e6, t_bundle, t_probe


def raw_difference(a: dict, b: dict) -> float:
    """Median |a/b - 1| over the graphs both runs timed (layers by id, stages by candidate/stage)."""
    d = [a["layers"][k] / b["layers"][k] - 1 for k in a["layers"] if k in b["layers"]]
    d += [ms / b["stages"][c][s] - 1 for c, st in a["stages"].items() for s, ms in st.items()
          if s in b["stages"].get(c, {})]
    return float(np.median(np.abs(d)))


def path_difference(costs: list, p: object, q: object) -> tuple[float, int]:
    d = []
    for cost in costs:
        a, b = cost.path_latency_ms(p)[1:], cost.path_latency_ms(q)[1:]
        d += [x / y - 1 for x, y in zip(a, b)]
    return float(np.median(np.abs(d))), len(d)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--candidates", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cands = held_out(args.candidates, args.seed)
    keys = {c.key for c in cands}
    costs = [candidate_cost(c) for c in cands]
    sizes, bundles, probes, directs, diffs, raws, floors = [], [], [], [], [], [], []
    previous = None
    for rep in range(1, args.repeats + 1):
        with tempfile.TemporaryDirectory() as tmp:
            via_probe, res, mb, t_bundle, t_probe = probe_profile(Path(tmp), args.seed, keys)
            t0 = time.perf_counter()
            direct = calibrate(seed=args.seed, exclude=keys, results_out=Path(tmp) / "direct.json")
            t_direct = time.perf_counter() - t0
            raw = raw_difference(res, read_results(Path(tmp) / "direct.json"))
        diff, n_paths = path_difference(costs, via_probe, direct)
        floor = f"; calibrate vs the previous calibrate {path_difference(costs, direct, previous)[0]:.1%} " \
                "(the noise floor)" if previous else ""
        if previous:
            floors.append(path_difference(costs, direct, previous)[0])
        previous = direct
        sizes.append(mb), bundles.append(t_bundle), probes.append(t_probe), directs.append(t_direct)
        diffs.append(diff), raws.append(raw)
        print(f"rep {rep}: bundle {mb:.2f} MB written in {t_bundle:.0f} s; probe {t_probe:.0f} s; explorer calibrate "
              f"{t_direct:.0f} s; probe vs calibrate: median per-path |difference| {diff:.1%} over {n_paths} paths "
              f"of {len(cands)} held-out candidates, median |difference| of the raw graph timings {raw:.1%}{floor}",
              flush=True)
    med = statistics.median
    print(f"median of {args.repeats}: bundle {med(sizes):.2f} MB (target <= 50 MB), probe {med(probes):.0f} s "
          f"(target <= 180 s), bundle export {med(bundles):.0f} s, explorer calibrate {med(directs):.0f} s, "
          f"probe vs calibrate {med(diffs):.1%} (target <= 5%), raw timings {med(raws):.1%}"
          + (f", calibrate vs calibrate {med(floors):.1%}" if floors else ""))


if __name__ == "__main__":
    main()
