"""The main job as a user runs it (``explorer search --device tx2``, what ``make search`` runs), then
the search quality that matters: the study's retrained winner against the paper design, both retrained
with a recipe 4x longer than the proxy (600 steps), anytime loss (tx2, U(0, 33 ms)). A search is worth
running if its winner beats the paper design; the goal is a ratio of 0.85 or better.

    ANYTIME_EXPLORER_CACHE=... python benchmarks/bench_search.py [--study bench-search] [--reps 3]
        [--skip-search] [-- more explorer search options]

With a warm cache (data, supernet) the search wall time is the search and the finalists only; the
supernet file records its own training time (bench_supernet.py reports it). Each repetition is one
retraining seed, winner and paper design in an order that rotates (trainings cached by _labels.py).
"""

import shutil
import subprocess
import sys
import time
from pathlib import Path

import optuna

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import recipe, score, standalone, with_seed  # noqa: E402
from harness import ROOT, Bench, interleave  # noqa: E402

from explorer.space import Candidate, paper_candidate  # noqa: E402
from explorer.study.results import baseline_trial, best_trial, finalists_frame, winner  # noqa: E402
from explorer.study.storage import load_study  # noqa: E402
from explorer.study import trial_record  # noqa: E402


def run_search(bench: Bench, study: str, reports: Path, extra: list[str]) -> None:
    shutil.rmtree(reports / study, ignore_errors=True)
    t0 = time.time()
    subprocess.run([sys.executable, "-m", "explorer", "search", "--device", "tx2", "--study", study,
                    "--reports", str(reports), *extra], check=True)
    bench.add(bench.figure("search_s", "search wall time (data and supernet from the cache when there)", "s",
                           "lower"), time.time() - t0)


if __name__ == "__main__":
    bench = Bench(__file__, "Search end to end: the retrained winner against the paper design", __doc__)
    ap = bench.parser()
    ap.add_argument("--study", default="bench-search")
    ap.add_argument("--reports", default=str(ROOT / "reports" / "bench"))
    ap.add_argument("--skip-search", action="store_true", help="read an existing study")
    ap.add_argument("search_args", nargs="*", help="more `explorer search` options (after --)")
    args = bench.parse_args(ap)
    reports = Path(args.reports)
    if not args.skip_search:
        run_search(bench, args.study, reports, args.search_args)
    study = load_study(args.study, None, reports)
    states = [t.state for t in study.trials]
    print(f"trials: { {s.name: states.count(s) for s in optuna.trial.TrialState if states.count(s)} }")
    est, paper_trial = best_trial(study), baseline_trial(study, "paper")
    if est and paper_trial:
        bench.add(bench.figure("estimate_over_paper", "best estimate / paper design's estimate", "x", "lower"),
                  est.values[0] / paper_trial.values[0])
    fin = finalists_frame(study)
    if not fin.empty:
        print(fin.to_string(index=False))
    win = winner(study)
    cand = Candidate.from_dict(trial_record(win).candidate)
    bench.note(f"study {args.study}: {len(study.trials)} trials; winner trial {win.number} {cand.key}: "
               f"{cand.describe()}")
    long = recipe(600)
    bench.figure("winner_loss", "retrained winner: anytime loss", "", "lower")
    bench.figure("paper_loss", "retrained paper design: anytime loss", "", "lower")
    bench.figure("winner_over_paper", "winner / paper design (goal 0.85 or better)", "x", "lower")
    for rep in bench.repetitions():
        got = interleave({"winner": lambda: score(standalone(cand, with_seed(long, rep))),
                          "paper": lambda: score(standalone(paper_candidate(), with_seed(long, rep)))}, rep)
        bench.add("winner_loss", got["winner"])
        bench.add("paper_loss", got["paper"])
        bench.add("winner_over_paper", got["winner"] / got["paper"])
    bench.finish()
