"""How the envelope's dedicated networks are chosen from a search's estimates, three rules for K
networks: ``front``, ``explorer envelope``'s, the point of the estimated front nearest each of K evenly
spaced costs from the cheapest to the front's end (``spread_along_front``); ``oracle``, those whose
oracle has the lowest estimated anytime loss, chosen one at a time; ``bins``, K evenly spaced deadlines
from the cheapest network to the budget's upper end and the most accurate estimate in each bin (late
deadlines get a network even where the estimate prefers a cheaper one). Each repetition is one
seed: a default search (``explorer search``'s pipeline with ``--time-limit T``, as in
bench_search_value), then the networks each rule chooses from its estimates, the winner and the paper
design retrained with one longer recipe (``--final-steps`` at the training size, then the finalists'
tuning at the deployment size) and measured at the deployment size on the first 96 validation frames;
a network several rules choose is trained once. The oracle is what an anytime network of the space can
approach, so the rule whose envelope has the lower anytime loss describes that limit better. Figures:
each rule's envelope anytime loss, the winner's ratio to it, when its last network is ready and how
many of its networks serve some budget.

    OMP_NUM_THREADS=1 python benchmarks/bench_envelope.py [--reps 3] [--time-s 300] [--networks 4]
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_search_value import (base_config, final_losses, final_recipe, final_recipe_note, prepare,  # noqa: E402
                                run_seeds, run_strategy, shared_arguments)
from harness import Bench  # noqa: E402

from explorer.anytime import anytime_loss, parse_budget  # noqa: E402
from explorer.space import paper_candidate  # noqa: E402
from explorer.study.envelope import envelope_steps, spread_along_front  # noqa: E402

RULES = ("oracle", "bins", "front")   # the record's order


def lowest_oracle(points: list[tuple], count: int, scan_error: float, budget) -> list:
    """``count`` of ``points`` (cost, estimated error, network) whose oracle has the lowest estimated
    anytime loss under ``budget`` (the scan's ``scan_error`` before the first), chosen one at a time:
    each time the point of the front that lowers it most."""
    front, lowest = [], scan_error
    for point in points:
        if point[1] < lowest:
            lowest = point[1]
            front.append(point)

    def oracle_loss(chosen: list) -> float:
        return anytime_loss(*envelope_steps(scan_error, [(c, e) for c, e, _ in chosen]), budget)

    chosen: list = []
    while len(chosen) < count:
        rest = [p for p in front if all(p is not q for q in chosen)]
        if not rest or min(oracle_loss(chosen + [p]) for p in rest) >= oracle_loss(chosen):
            break
        chosen.append(min(rest, key=lambda p: oracle_loss(chosen + [p])))
    return [network for _, _, network in sorted(chosen, key=lambda p: p[0])]


def best_per_bin(points: list[tuple], count: int, upper: float) -> list:
    """``count`` evenly spaced deadlines from the cheapest point's cost to ``upper``; for each, the point
    with the lowest estimated error among those ready after the previous deadline and by this one (a bin
    with none leaves its place to the most accurate others)."""
    if len(points) <= count:
        return [network for _, _, network in points]
    chosen, after = [], -math.inf
    for deadline in np.linspace(points[0][0], upper, count):
        in_bin = [p for p in points if after < p[0] <= deadline]
        if in_bin:
            chosen.append(min(in_bin, key=lambda p: p[1]))
        after = deadline
    chosen += sorted((p for p in points if all(p is not q for q in chosen)), key=lambda p: p[1])[:count - len(chosen)]
    return [network for _, _, network in sorted(chosen, key=lambda p: p[0])]


def declare(bench: Bench, final_steps: int) -> None:
    recipe = f"after {final_steps} steps + tuning at 224x224"
    for rule in RULES:
        bench.figure(f"envelope_anytime_{rule}", f"{rule}: the envelope's anytime loss {recipe}", "m", better="lower")
        bench.figure(f"envelope_ratio_{rule}", f"{rule}: the winner's anytime loss / the envelope's", "")
        bench.figure(f"last_ready_{rule}", f"{rule}: when the envelope's last network is ready", "ms")
        bench.figure(f"serving_{rule}", f"{rule}: networks serving some budget", "")
    bench.figure("ratio_default", f"the winner / the paper design, anytime loss {recipe}", "", better="lower")
    bench.figure("supernet_steps", "supernet steps trained inside T", "")


def one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data) -> None:
    best, info = run_strategy("default", seed, args, work, data_cache)
    bench.add("supernet_steps", info["supernet_steps"])
    points, budget = info["estimated_networks"], base_config(seed, "final").budgets[0]
    chosen = {"front": spread_along_front(points, args.networks),
              "oracle": lowest_oracle(points, args.networks, info["scan_error"], budget),
              "bins": best_per_bin(points, args.networks, parse_budget(budget).upper)}
    for rule in RULES:
        print(f"  {rule}: {[(n.key, n.path) for n in chosen[rule]]}", flush=True)
    paper, recipe = paper_candidate(), final_recipe(args.final_steps)
    networks = [n for rule in RULES for n in chosen[rule]]
    trained = final_losses([(c.key, c, recipe) for c in (paper, best)]
                           + [(n.key, n.candidate, n.recipe(recipe)) for n in networks], seed, data)
    winner_loss = anytime_loss(*trained[best.key], budget)
    bench.add("ratio_default", winner_loss / anytime_loss(*trained[paper.key], budget))
    scan = trained[paper.key][1][0]
    for rule in RULES:
        steps = envelope_steps(scan, [(trained[n.key][0][n.path], trained[n.key][1][n.path]) for n in chosen[rule]])
        loss = anytime_loss(*steps, budget)
        print(f"  {rule}: anytime loss {loss:.4f} from steps {[(round(c, 1), round(e, 4)) for c, e in zip(*steps)]}",
              flush=True)
        bench.add(f"envelope_anytime_{rule}", loss)
        bench.add(f"envelope_ratio_{rule}", winner_loss / loss)
        bench.add(f"last_ready_{rule}", steps[0][-1])
        bench.add(f"serving_{rule}", len(steps[0]) - 1)


def main() -> None:
    bench = Bench(__file__, "the envelope's networks: three ways to choose them from a search's estimates", __doc__)
    ap = bench.parser()
    shared_arguments(ap, time_s=300.0)
    ap.add_argument("--networks", type=int, default=4, help="dedicated networks each rule chooses (default 4)")
    args = bench.parse_args(ap)
    args.envelope_networks = args.networks    # what run_strategy passes on
    config, data = prepare(args.threads)
    declare(bench, args.final_steps)
    bench.note(f"cpu, torch threads {args.threads}; a default search of T = {args.time_s:g} s a seed (no baselines); "
               f"{args.networks} networks a rule; {final_recipe_note(config, args.final_steps)}; {config.device}, "
               f"{config.budgets[0]}")
    run_seeds(bench, one_seed, args, data, "bench-envelope-")
    bench.finish()


if __name__ == "__main__":
    main()
