"""The main job as a user runs it (`explorer search --device tx2`, what `make search` runs), then the
search quality that matters: the study's retrained winner against the paper design, both retrained
with a recipe 4x longer than the proxy (600 steps), 2 seeds each, mean anytime loss (tx2, U(0, 33 ms)).

    ANYTIME_EXPLORER_CACHE=... .venv/bin/python benchmarks/bench_search.py [--study bench-search]

With a warm cache (data, supernet) the wall time printed is the search and the finalists only; the
supernet file records its own training time (benchmarks/bench_supernet.py prints it).
"""

import argparse
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import optuna

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import recipe, score, standalone, with_seed  # noqa: E402

from explorer.study.results import baseline_trial, best_trial, finalists_frame, winner  # noqa: E402
from explorer.space import Candidate, paper_candidate  # noqa: E402
from explorer.study.storage import load_study  # noqa: E402

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--study", default="bench-search")
    ap.add_argument("--reports", default="/tmp/anytime-bench-reports")
    ap.add_argument("--skip-search", action="store_true", help="read an existing study")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("search_args", nargs="*", help="more `explorer search` options (after --)")
    args = ap.parse_args()
    reports = Path(args.reports)
    if not args.skip_search:
        shutil.rmtree(reports / args.study, ignore_errors=True)
        t0 = time.time()
        subprocess.run([sys.executable, "-m", "explorer", "search", "--device", "tx2", "--study", args.study,
                        "--reports", str(reports), *args.search_args], check=True)
        print(f"search wall time {time.time() - t0:.0f} s (data and supernet from the cache when there)")
    study = load_study(args.study, None, reports)
    states = [t.state for t in study.trials]
    print(f"trials: { {s.name: states.count(s) for s in optuna.trial.TrialState if states.count(s)} }")
    est = best_trial(study)
    print(f"best estimate: trial {est.number} {est.values[0]:.4f}; paper design estimate "
          f"{baseline_trial(study, 'paper').values[0]:.4f}" if est and baseline_trial(study, "paper") else "")
    fin = finalists_frame(study)
    if not fin.empty:
        print(fin.to_string(index=False))
    win = winner(study)
    cand = Candidate.from_dict(win.user_attrs["candidate"])
    print(f"winner: trial {win.number} {cand.key}: {cand.describe()}")
    long = recipe(600)
    w, p = [], []
    for seed in range(args.seeds):   # interleaved: winner, paper, winner, paper
        w.append(score(standalone(cand, with_seed(long, seed))))
        p.append(score(standalone(paper_candidate(), with_seed(long, seed))))
        print(f"  seed {seed}: winner {w[-1]:.4f}, paper design {p[-1]:.4f}, ratio {w[-1] / p[-1]:.3f}")
    print(f"retrained {long.steps} steps, mean of {args.seeds} seeds: winner {statistics.mean(w):.4f}, paper design "
          f"{statistics.mean(p):.4f}, ratio {statistics.mean(w) / statistics.mean(p):.3f} (goal 0.85 or better)")
