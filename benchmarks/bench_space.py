"""Cost only (no training): how early the first output comes in the widened default space (exits in
the image encoder, a learned LiDAR-only path, stage order) against the space before the widening,
and what it takes to cost each. The widening exists to offer earlier first outputs; the earliest and
median first-exit times on the chosen device say how much earlier.

    python benchmarks/bench_space.py [--reps 3] [--sample 20000] [--device tx2]

The space before the widening is enumerated whole; the widened one (over a million candidates) is
sampled at random (a new seed each repetition), and its earliest first exit is also found exactly (the
LiDAR-only path, or an encoder exit of the narrowest encoder, whichever comes first). The enumeration
and the sampling alternate within each repetition.
"""

from __future__ import annotations

import statistics
import time

import yaml

from explorer.cost import candidate_cost, get_device
from explorer.space import SearchSpace, paper_candidate
from explorer.study.enumerate import enumerate_space

from harness import Bench, interleave


def space_before_widening(wide: SearchSpace) -> SearchSpace:
    with open(wide.source) as f:
        raw = yaml.safe_load(f)
    raw["image_encoder"].pop("exits")
    raw["lidar_encoder"].pop("first")
    raw["exits"].pop("lidar_only")
    return SearchSpace.from_dict(raw, source="before widening")


def timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    got = fn()
    return time.perf_counter() - t0, got


if __name__ == "__main__":
    bench = Bench(__file__, "First-exit latency of the widened search space against the space before it", __doc__)
    ap = bench.parser()
    ap.add_argument("--sample", type=int, default=20000)
    ap.add_argument("--device", default="tx2")
    args = bench.parse_args(ap)
    wide = SearchSpace.from_yaml("anytime_depth")
    before = space_before_widening(wide)
    dev = get_device(args.device)
    # the exact earliest: every candidate's first path is one of these few stage prefixes
    probes = [c for c in wide.random_candidates(4000, seed=1)
              if c.lidar_exit or (c.encoder_exits and c.width_mult == min(wide.width_mult))]
    exact = min(candidate_cost(c).path_latency_ms(dev)[1] for c in probes)
    lidar = next(c for c in probes if c.lidar_exit)
    bench.note(f"device {dev.name}; {before.size:,} candidates before the widening, {wide.size:,} after; "
               f"{args.sample:,} sampled per repetition; the LiDAR-only path costs "
               f"{candidate_cost(lidar).path_latency_ms(dev)[1]:.3f} ms (inference overhead "
               f"{dev.inference_overhead_ms:.3f} ms included)")
    bench.figure("before_earliest_ms", "earliest first exit before the widening", "ms", "lower")
    bench.figure("before_median_ms", "median first exit before the widening", "ms", "lower")
    bench.figure("widened_earliest_sampled_ms", "earliest first exit, widened (sample)", "ms", "lower")
    bench.figure("widened_median_sampled_ms", "median first exit, widened (sample)", "ms", "lower")
    bench.figure("widened_earliest_exact_ms", "earliest first exit, widened (exact)", "ms", "lower")
    bench.figure("paper_first_ms", "paper design's first exit", "ms", None)
    bench.figure("enumerate_s", "enumerating the space before the widening", "s", "lower")
    bench.figure("sample_s", f"costing {args.sample:,} widened candidates", "s", "lower")
    paper_first = candidate_cost(paper_candidate()).path_latency_ms(dev)[1]
    for rep in bench.repetitions():
        got = interleave({
            "before": lambda: timed(lambda: enumerate_space(before, dev, "time:uniform:33ms")),
            "widened": lambda: timed(lambda: [candidate_cost(c).path_latency_ms(dev)[1]
                                              for c in wide.random_candidates(args.sample, seed=rep)])}, rep)
        (t_old, old), (t_wide, firsts) = got["before"], got["widened"]
        bench.add("before_earliest_ms", old["first_exit_ms"].min())
        bench.add("before_median_ms", old["first_exit_ms"].median())
        bench.add("widened_earliest_sampled_ms", min(firsts))
        bench.add("widened_median_sampled_ms", statistics.median(firsts))
        bench.add("widened_earliest_exact_ms", exact)
        bench.add("paper_first_ms", paper_first)
        bench.add("enumerate_s", t_old)
        bench.add("sample_s", t_wide)
    bench.finish()
