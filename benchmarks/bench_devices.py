"""Device cost models: the shipped fits against their calibration figures, then the host:
calibrate with onnxruntime, predict 20+ random default-space candidates that were not in the sweep,
and compare with measurement.

    .venv/bin/python benchmarks/bench_devices.py [--candidates 24] [--data ../shared/data]
"""

import argparse
import random
import time
from pathlib import Path

import numpy as np

from explorer.cost import candidate_cost, get_device
from explorer.cost.calibrate import calibrate
from explorer.cost.fit import (FASTDEPTH_TX2_MS, PAPER_RPI4_TABLE2, PAPER_TX2_PATHS_MS, Observation, errors,
                               kernel_workloads, rpi4_table2)
from explorer.cost.measure import measure_candidate
from explorer.space import SearchSpace, fastdepth_candidate, paper_candidate


def shipped(data: Path) -> None:
    csv = data / "tx2-tvm-kernels" / "kernels.csv"
    for target, name in (("gpu", "tx2"), ("cpu", "tx2-cpu")):
        prof = get_device(name)
        obs = [Observation(w.layer, [w], ms) for w, ms in kernel_workloads(csv, target)]
        err = errors(prof, obs)["error"].abs()
        print(f"{name}: {len(obs)} measured kernels, median |error| {err.median():.1%} (target <= 20%), "
              f"within 10%: {(err <= 0.1).mean():.0%}")
    tx2 = get_device("tx2")
    ms = candidate_cost(paper_candidate()).path_latency_ms(tx2)[1:]
    for i, (got, want) in enumerate(zip(ms, PAPER_TX2_PATHS_MS), start=1):
        print(f"tx2 paper design path {i}: {got:.2f} ms vs {want} ms ({got / want - 1:+.1%}, target within 10%)")
    fd = candidate_cost(fastdepth_candidate()).path_latency_ms(tx2)[-1]
    print(f"tx2 FastDepth-like: {fd:.2f} ms vs {FASTDEPTH_TX2_MS} ms ({fd / FASTDEPTH_TX2_MS - 1:+.1%})")
    print(f"tx2 energy: {tx2.energy_j(6.37):.3f} J at 6.37 ms (paper 0.2 J), {tx2.energy_j(554.7):.3f} J at 554.7 ms (paper 6.244 J)")
    for spec, got in rpi4_table2(get_device("rpi4")).items():
        print(f"rpi4 {spec}: {got:.3f} vs Table 2 {PAPER_RPI4_TABLE2[spec]} ({got - PAPER_RPI4_TABLE2[spec]:+.3f}, target within 0.03)")
    for c in get_device("rpi4").provenance["checks"]:
        if "target_ms" in c:
            print(f"rpi4 check {c['what']}: {c['predicted_ms']} ms vs {c['target_ms']} ms")


def host(n: int, seed: int) -> None:
    cands = random.Random(seed + 1).sample(list(SearchSpace.from_yaml("anytime_depth").enumerate()), n)
    t0 = time.perf_counter()
    prof = calibrate(seed=seed, exclude={c.key for c in cands})  # held out: never in the sweep
    print(f"\nhost calibration: {time.perf_counter() - t0:.0f} s; {prof.provenance['conditions']['threads']} threads, "
          f"onnxruntime {prof.provenance['conditions']['onnxruntime']}")
    for fit in prof.provenance["fit"]:
        print(f"  fit on {fit['what']}: median |error| {fit['median_abs_error']:.1%}")
    path_err, last_err = [], []
    for c in cands:
        m = measure_candidate(c, repeats=30)
        pred = candidate_cost(c).path_latency_ms(prof)
        e = [p / q - 1 for p, q in zip(pred[1:], m.path_ms[1:])]
        path_err += e
        last_err.append(e[-1])
        print(f"  {c.key}: measured {' '.join(f'{x:6.2f}' for x in m.path_ms[1:])} ms | predicted "
              f"{' '.join(f'{x:6.2f}' for x in pred[1:])} ms")
    a = np.abs(path_err)
    print(f"host: {n} held-out candidates, {len(a)} paths: median |error| {np.median(a):.1%} "
          f"(target <= 10%, aim 5%), within 10%: {(a <= 0.1).mean():.0%}, last path median |error| "
          f"{np.median(np.abs(last_err)):.1%}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    ap.add_argument("--candidates", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if Path(args.data).is_dir():
        shipped(Path(args.data))
    host(args.candidates, args.seed)
