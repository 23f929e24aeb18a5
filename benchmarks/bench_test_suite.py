"""How long ``make test`` takes with its default workers (pytest-xdist, one process per core, at most
4) against ``TEST_WORKERS=0`` (every test in one process), on this machine: the README's command
itself, run from the repository root, the two interleaved (their order rotating from repetition to
repetition). Figures: each one's wall time, the ratio of the two in the same repetition, and the tests
each passed (a run that fails stops the benchmark: a faster failure is no figure).

    python benchmarks/bench_test_suite.py [--reps 3]

Nothing else should run beside it: both runs use every core.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import ROOT, Bench, rotated  # noqa: E402

#: the runs compared: their name and the make variables that make them
RUNS = {"default": [], "one_process": ["TEST_WORKERS=0"]}
PASSED = re.compile(r"(\d+) passed")


def make_test(variables: list[str]) -> tuple[float, int]:
    """``make test`` with ``variables``: (its wall seconds, the tests passed)."""
    started = time.perf_counter()
    done = subprocess.run(["make", "-s", "test", *variables], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    seconds = time.perf_counter() - started
    tail = (done.stdout + done.stderr).strip().splitlines()[-1:] or [""]
    if done.returncode != 0:
        raise SystemExit(f"make test {' '.join(variables)} failed (exit {done.returncode}): {tail[0]}")
    passed = PASSED.search(tail[0])
    print(f"  make test {' '.join(variables) or '(default workers)'}: {seconds:.0f} s, {tail[0]}", flush=True)
    return seconds, int(passed.group(1)) if passed else 0


def main() -> None:
    bench = Bench(__file__, "make test: one process per core against one process", __doc__)
    bench.parse_args(bench.parser())
    for name in RUNS:
        bench.figure(f"wall_s_{name}", f"make test, {name.replace('_', ' ')}: wall time", "s", better="lower")
        bench.figure(f"passed_{name}", f"make test, {name.replace('_', ' ')}: tests passed", "")
    bench.figure("speedup", "one process's wall time / the default's, same repetition", "x", better="higher")
    bench.note(f"{os.cpu_count()} cores; make test's default workers min(cores, 4); "
               f"the suite as of this commit, the shared data {'present' if (ROOT.parent / 'shared' / 'data').is_dir() else 'absent'}")
    for rep in bench.repetitions():
        wall = {}
        for name in rotated(list(RUNS), rep):
            wall[name], passed = make_test(RUNS[name])
            bench.add(f"wall_s_{name}", wall[name])
            bench.add(f"passed_{name}", passed)
        bench.add("speedup", wall["one_process"] / wall["default"])
    bench.finish()


if __name__ == "__main__":
    main()
