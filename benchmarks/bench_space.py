"""Cost only (no training): how early the first output comes in the widened default space (exits in
the image encoder, a learned LiDAR-only path, stage order) against the space before the widening.

    .venv/bin/python benchmarks/bench_space.py [--sample 20000]

The space before the widening is enumerated whole; the widened one (over a million candidates) is
sampled at random, and its earliest first exit is also found exactly (the LiDAR-only path, or an
encoder exit of the narrowest encoder, whichever comes first).
"""

from __future__ import annotations

import argparse
import statistics
import time

import pandas as pd

from explorer.cost import candidate_cost, get_device
from explorer.study.enumerate import enumerate_space
from explorer.space import SearchSpace, paper_candidate

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--sample", type=int, default=20000)
    ap.add_argument("--device", default="tx2")
    args = ap.parse_args()
    wide = SearchSpace.from_yaml("anytime_depth")
    import yaml
    raw = yaml.safe_load(open(wide.source))
    raw["image_encoder"].pop("exits")
    raw["lidar_encoder"].pop("first")
    raw["exits"].pop("lidar_only")
    before = SearchSpace.from_dict(raw, source="before widening")
    dev = get_device(args.device)
    t0 = time.perf_counter()
    old = enumerate_space(before, dev, "time:uniform:33ms")
    print(f"before the widening: {before.size:,} candidates, enumerated in {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()
    firsts = []
    for c in wide.random_candidates(args.sample, seed=0):
        firsts.append(candidate_cost(c).path_latency_ms(dev)[1])
    print(f"widened: {wide.size:,} candidates; {len(firsts):,} sampled and costed in {time.perf_counter() - t0:.0f} s")
    # the exact earliest: every candidate's first path is one of these few stage prefixes
    probes = [c for c in wide.random_candidates(4000, seed=1)
              if c.lidar_exit or (c.encoder_exits and c.width_mult == min(wide.width_mult))]
    exact = min(candidate_cost(c).path_latency_ms(dev)[1] for c in probes)
    paper_first = candidate_cost(paper_candidate()).path_latency_ms(dev)[1]
    rows = [
        {"space": "before widening", "earliest first exit ms": old["first_exit_ms"].min(),
         "median first exit ms": old["first_exit_ms"].median(), "candidates": before.size},
        {"space": "widened (sample)", "earliest first exit ms": min(firsts),
         "median first exit ms": statistics.median(firsts), "candidates": wide.size},
        {"space": "widened (exact earliest)", "earliest first exit ms": exact, "median first exit ms": float("nan"),
         "candidates": wide.size},
        {"space": "paper design", "earliest first exit ms": paper_first, "median first exit ms": paper_first,
         "candidates": 1}]
    print(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    lidar = next(c for c in probes if c.lidar_exit)
    print(f"LiDAR-only path on {dev.name}: {candidate_cost(lidar).path_latency_ms(dev)[1]:.3f} ms "
          f"(inference overhead {dev.inference_overhead_ms:.3f} ms included)")
