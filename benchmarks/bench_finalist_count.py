"""More finalists, each retrained briefly, against the few a time limit plans: the same wall time,
two ways to spend the finalists' share of it. Each repetition is one seed, the two interleaved (their
order rotates from seed to seed), each given ``--time-s`` T seconds with everything it needs, as in
bench_search_value:

- ``default``: ``explorer search --time-limit T`` with every setting left to the plan;
- ``screened``: the same with ``--finalists K --finalist-steps S`` set (``--finalists``, default 5;
  ``--steps``, default 150), which the plan keeps, shrinking the supernet and sampling instead: the
  estimate's best K, one per image encoder first, retrained briefly, the best measured one the winner.
  It is the first rung of successive halving, and the question is whether retraining more of the
  estimate's best ranks them better than retraining fewer for longer (in bench_search_value, random
  candidates retrained briefly, as many as T holds, had a median no worse than the search's).

T is 420 s by default: at 300 s on a 2-core CPU the supernet's 300 steps and the least sampling leave
room for 2 finalists of 150 steps, since each one's tuning at 224x224 costs about as much as its
training at 64x64.

Then each seed's two winners and the paper design are retrained with one longer recipe
(``--final-steps`` at the training size, then the finalists' tuning at the deployment size), with
that seed, and measured at the deployment size on the first 96 validation frames, as in
bench_search_value. Figures: each winner's anytime loss over the paper design's (``ratio_<strategy>``),
the paper design's (to set beside bench_search_value's at the same seeds), the finalists each
retrained, their steps and the supernet steps each trained inside T.

    OMP_NUM_THREADS=1 python benchmarks/bench_finalist_count.py [--reps 3] [--time-s 420] [--finalists 5]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_search_value import (base_config, final_losses, final_recipe, final_recipe_note, prepare,  # noqa: E402
                                run_seeds, run_strategy, shared_arguments)
from harness import Bench, rotated  # noqa: E402

from explorer.anytime import anytime_loss  # noqa: E402
from explorer.space import paper_candidate  # noqa: E402

STRATEGIES = ("default", "screened")
#: what the screened strategy leaves to the plan: the finalists' number and steps are set
SCREENED_FREE = frozenset({"supernet_steps"})


def declare(bench: Bench, seconds: float, final_steps: int) -> None:
    for name in STRATEGIES:
        bench.figure(f"ratio_{name}", f"{name}: winner / paper design, anytime loss after {final_steps} steps "
                     "+ tuning at 224x224", "", better="lower")
    for name in STRATEGIES:
        bench.figure(f"retrained_{name}", f"{name}: finalists retrained inside T = {seconds:g} s", "")
        bench.figure(f"finalist_steps_{name}", f"{name}: each finalist's steps at the training size", "")
        bench.figure(f"supernet_steps_{name}", f"{name}: supernet steps trained inside T", "")
        bench.figure(f"seconds_{name}", f"{name}: wall time", "s")
    bench.figure("paper_anytime", f"paper design: anytime loss after {final_steps} steps + tuning at 224x224", "m",
                 better="lower")


def one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data) -> None:
    """The two strategies for ``seed``, in the repetition's order; then their winners and the paper
    design retrained with the longer recipe (a network both strategies chose is trained once)."""
    winners = {}
    for name in rotated(list(STRATEGIES), seed):
        if name == "screened":
            changes = {"finalists": args.finalists, "finalist_steps": args.steps}
            winners[name], info = run_strategy(name, seed, args, work, data_cache, changes, SCREENED_FREE)
        else:
            winners[name], info = run_strategy(name, seed, args, work, data_cache)
        for figure in ("seconds", "retrained", "supernet_steps", "finalist_steps"):
            bench.add(f"{figure}_{name}", info[figure])
    paper, recipe = paper_candidate(), final_recipe(args.final_steps)
    trained = final_losses([(c.key, c, recipe) for c in (paper, *winners.values())], seed, data)
    budget = base_config(seed, "final").budgets[0]
    paper_loss = anytime_loss(*trained[paper.key], budget)
    bench.add("paper_anytime", paper_loss)
    for name in STRATEGIES:
        bench.add(f"ratio_{name}", anytime_loss(*trained[winners[name].key], budget) / paper_loss)


def main() -> None:
    bench = Bench(__file__, "more finalists retrained briefly against the few a time limit plans", __doc__)
    ap = bench.parser()
    shared_arguments(ap, time_s=420.0)
    ap.add_argument("--finalists", type=int, default=5, help="the screened strategy's finalists (default 5)")
    ap.add_argument("--steps", type=int, default=150, help="the screened strategy's steps a finalist at the "
                    "training size, before the tuning (default 150)")
    args = bench.parse_args(ap)
    args.envelope_networks = 1    # what run_strategy passes on: the dedicated networks are not retrained here
    config, data = prepare(args.threads)
    declare(bench, args.time_s, args.final_steps)
    bench.note(f"cpu, torch threads {args.threads}; T = {args.time_s:g} s a strategy and seed, supernet and data "
               f"loading inside it (a fresh cache each run); no baselines retrained inside T; screened: "
               f"{args.finalists} finalists of {args.steps} steps + tuning; "
               f"{final_recipe_note(config, args.final_steps)}; {config.device}, {config.budgets[0]}")
    run_seeds(bench, one_seed, args, data, "bench-finalist-count-")
    bench.finish()


if __name__ == "__main__":
    main()
