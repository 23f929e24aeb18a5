"""`make search` as a new user runs it, on a machine that other work keeps busy: a fresh clone of the
current commit, a fresh data and supernet cache, ``--loads`` CPU-bound processes running beside it
from start to end. The figures: the wall time of the whole ``make search`` (setup included) against
its 16-minute limit, and whether the summary told the truth when no searched candidate beat a
baseline after retraining (it must say so, not call the candidate a winner).

    python benchmarks/bench_make_search_load.py [--loads 2] [--reps 3] [--limit-s 960]

Each repetition clones, sets up its own .venv (pip's cache helps the later ones) and generates
its own data, so that none of them starts warm. About 17 minutes a repetition.
"""

import math
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import ROOT, Bench  # noqa: E402

from explorer.study.results import is_retrained, scored_trials, unbeaten_baseline, winner  # noqa: E402
from explorer.study.storage import load_study  # noqa: E402
from explorer.study import trial_record  # noqa: E402

STUDY = "tx2-anytime_depth"


def _spin() -> None:
    while True:
        pass


def _summary_is_honest(clone: Path, stdout: str) -> tuple[float, bool]:
    """(retrained winner / best retrained baseline, whether the summary said what it had to)."""
    study = load_study(STUDY, None, clone / "reports")
    best = winner(study)
    bases = [t for t in scored_trials(study) if is_retrained(t) and trial_record(t).baseline]
    base = min(bases, key=lambda t: t.values[0], default=None)
    ratio = best.values[0] / base.values[0] if best and base and is_retrained(best) else math.nan
    unbeaten = unbeaten_baseline(study) is not None
    said = "no searched candidate beat" in stdout
    return ratio, said == unbeaten and (ratio <= 1.0 or said)


def one_run(bench: Bench, loads: int, limit_s: float, rep: int) -> None:
    work = Path(tempfile.mkdtemp(prefix="bench-make-search-"))
    try:
        clone = work / "clone"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(work / "cache"), "SEARCH_LIMIT_S": str(int(limit_s))}
        spinners = [mp.get_context("fork").Process(target=_spin, daemon=True) for _ in range(loads)]
        for p in spinners:
            p.start()
        t0 = time.time()
        try:
            run = subprocess.run(["make", "search"], cwd=clone, env=env, capture_output=True, text=True)
        finally:
            for p in spinners:
                p.terminate()
        wall = time.time() - t0
        tail = "\n".join(run.stdout.splitlines()[-25:])
        print(f"  rep {rep}: make search exit {run.returncode}, {wall:.0f} s\n{tail}", flush=True)
        if run.returncode != 0:
            raise SystemExit(f"make search failed:\n{run.stderr[-2000:]}")
        ratio, honest = _summary_is_honest(clone, run.stdout)
        bench.add("wall_s", wall)
        bench.add("over_limit", wall / limit_s)
        bench.add("winner_over_best_baseline", ratio)
        bench.add("summary_honest", 1.0 if honest else 0.0)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    bench = Bench(__file__, "make search from a fresh clone under CPU-bound load: wall time against its limit",
                  __doc__)
    ap = bench.parser()
    ap.add_argument("--loads", type=int, default=2, help="CPU-bound processes running beside it")
    ap.add_argument("--limit-s", type=float, default=960.0, help="make search's limit (SEARCH_LIMIT_S)")
    args = bench.parse_args(ap)
    bench.note(f"{args.loads} CPU-bound load(s) on {os.cpu_count()} cores; limit {args.limit_s:.0f} s; "
               "fresh clone, .venv and cache each repetition; the clone is of the last commit, so what is "
               "uncommitted in this checkout (the record's dirty flag) is not measured")
    bench.figure("wall_s", "make search wall time, setup included", "s", "lower")
    bench.figure("over_limit", "wall time / limit (target 1.10 or less)", "x", "lower")
    bench.figure("winner_over_best_baseline", "retrained winner / best retrained baseline", "x", "lower")
    bench.figure("summary_honest", "summary names a baseline the best model when no candidate beat it (1 = yes)",
                 "", "higher")
    for rep in bench.repetitions():
        one_run(bench, args.loads, args.limit_s, rep)
    bench.finish()
