"""Cost-only enumeration of the whole default space (``explorer enumerate``): every candidate's
parameters, MACs, per-path latency and energy and the cost side of the anytime loss, written to a CSV
file, with the Pareto front of the default cost columns over every candidate. The array arithmetic
(each distinct front and back of the stage list costed once, then summed per candidate with numpy)
against the per-candidate computation it reproduces exactly (``candidate_rows``), which is too slow
to run whole: it is timed on the space's first candidates and extrapolated to the whole space.

    python benchmarks/bench_enumerate.py [--reps 3] [--device tx2] [--slice 100000]

Both start cold in every repetition (the stage cost cache is cleared, so both trace the distinct
stages they need) and alternate in a rotating order. Before the repetitions, the two are checked to
give the same rows on the slice's first candidates.
"""

from __future__ import annotations

import itertools
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from explorer.cost.workloads import stage_cost
from explorer.space import SearchSpace
from explorer.study.enumerate import candidate_rows, space_grid, write_enumeration

from harness import Bench, interleave

BUDGET = "time:uniform:33ms"


def whole_space(space: SearchSpace, device: str, folder: Path) -> tuple[float, int, int]:
    """(seconds, candidates, CSV bytes) of enumerating the whole space to a CSV file, from cold."""
    stage_cost.cache_clear()
    t0 = time.perf_counter()
    done = write_enumeration(space, device, BUDGET, csv=folder / "all.csv")
    seconds = time.perf_counter() - t0
    return seconds, done.size, (folder / "all.csv").stat().st_size


def per_candidate(space: SearchSpace, device: str, count: int) -> float:
    """Seconds the per-candidate computation takes for the space's first ``count`` candidates, from cold."""
    stage_cost.cache_clear()
    t0 = time.perf_counter()
    for _ in itertools.islice(candidate_rows(space, device, BUDGET), count):
        pass
    return time.perf_counter() - t0


def check_same_rows(space: SearchSpace, device: str, count: int) -> None:
    want = pd.DataFrame(list(itertools.islice(candidate_rows(space, device, BUDGET), count)))
    grid = space_grid(space, device, BUDGET)
    pd.testing.assert_frame_equal(grid.frame(grid.costs(np.arange(count))), want, check_exact=True)


if __name__ == "__main__":
    bench = Bench(__file__, "Enumerating the whole default space: array arithmetic against per candidate", __doc__)
    ap = bench.parser()
    ap.add_argument("--device", default="tx2")
    ap.add_argument("--slice", type=int, default=100_000, help="candidates the per-candidate run costs")
    args = bench.parse_args(ap)
    space = SearchSpace.from_yaml("anytime_depth")
    check_same_rows(space, args.device, 5000)
    bench.note(f"space anytime_depth ({space.size:,} candidates), device {args.device}, budget {BUDGET}, "
               f"224x224; the array run writes every row to a CSV file and finds the front of p_path0, "
               f"last_exit_ms and params; the per-candidate run costs the first {args.slice:,} candidates "
               "and its whole-space time is extrapolated from their rate; both gave the same rows on the "
               "first 5,000 candidates")
    bench.figure("whole_space_s", "whole space to CSV, array arithmetic", "s", "lower")
    bench.figure("array_per_s", "candidates per second, array arithmetic", "1/s", "higher")
    bench.figure("slice_s", f"first {args.slice:,} candidates, per candidate", "s", "lower")
    bench.figure("per_candidate_per_s", "candidates per second, per candidate", "1/s", "higher")
    bench.figure("per_candidate_whole_s", "whole space per candidate (extrapolated)", "s", "lower")
    bench.figure("speedup", "per candidate (extrapolated) / array arithmetic", "x", "higher")
    bench.figure("csv_mb", "CSV written", "MB", None)
    with tempfile.TemporaryDirectory() as tmp:
        for rep in bench.repetitions():
            got = interleave({"array": lambda: whole_space(space, args.device, Path(tmp)),
                              "per_candidate": lambda: per_candidate(space, args.device, args.slice)}, rep)
            (seconds, size, size_bytes), slice_s = got["array"], got["per_candidate"]
            rate = args.slice / slice_s
            bench.add("whole_space_s", seconds)
            bench.add("array_per_s", size / seconds)
            bench.add("slice_s", slice_s)
            bench.add("per_candidate_per_s", rate)
            bench.add("per_candidate_whole_s", size / rate)
            bench.add("speedup", size / rate / seconds)
            bench.add("csv_mb", size_bytes / 1e6)
    bench.finish()
