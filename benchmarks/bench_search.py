"""The main job as a user runs it: `explorer search --device tx2 --timeout 10m`, then the figures of
the study (trials completed, best anytime loss, ratio to the paper-design baseline) and the rate of
cost-only enumeration of the default space.

    .venv/bin/python benchmarks/bench_search.py [--timeout 10m] [--study bench-search]
"""

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

import optuna

from explorer.enumerate import enumerate_space
from explorer.results import baseline_trial, best_trial
from explorer.space import SearchSpace
from explorer.storage import load_study

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--timeout", default="10m")
    ap.add_argument("--study", default="bench-search")
    ap.add_argument("--reports", default="/tmp/anytime-bench-reports")
    ap.add_argument("--skip-search", action="store_true")
    args = ap.parse_args()
    reports = Path(args.reports)
    if not args.skip_search:
        shutil.rmtree(reports / args.study, ignore_errors=True)
        t0 = time.time()
        subprocess.run([sys.executable, "-m", "explorer", "search", "--device", "tx2", "--timeout", args.timeout,
                        "--study", args.study, "--reports", str(reports)], check=True)
        print(f"search wall time {time.time() - t0:.0f} s (synthetic data generation included if not cached)")
    study = load_study(args.study, None, reports)
    states = [t.state for t in study.trials]
    done = {s.name: states.count(s) for s in optuna.trial.TrialState if states.count(s)}
    best, paper = best_trial(study), baseline_trial(study, "paper")
    print(f"trials: {done}")
    if best and paper:
        print(f"best anytime loss {best.values[0]:.4f} (trial {best.number}); paper design {paper.values[0]:.4f}; "
              f"ratio {best.values[0] / paper.values[0]:.3f} (goal < 0.9)")
    for name in ("paper-nee", "fastdepth"):
        t = baseline_trial(study, name)
        if t:
            print(f"baseline {name}: {t.values[0]:.4f}")
    space = SearchSpace.from_yaml("anytime_depth")
    t0 = time.perf_counter()
    frame = enumerate_space(space, "tx2", "time:uniform:33ms")
    dt = time.perf_counter() - t0
    print(f"enumeration: {len(frame):,} candidates in {dt:.1f} s ({len(frame) / dt:,.0f}/s, goal < 60 s)")
