"""Does the search earn its time? Strategies that spend the same wall time on this machine finding a
network of the default space, each seed's winners retrained with one longer recipe and measured at the
deployment size (``experiments.lib.comparison``):

- ``search_value``: TPE, random sampling, random retraining and proxy training at T = 300 s;
- ``sampler_value``: TPE against random sampling at ``make search``'s length (T = 900 s);
- ``search_long``: the search against random retraining at ``make search``'s length;
- ``envelope``: three ways to choose the envelope's networks from a search's estimates;
- ``finalist_count``: more finalists retrained briefly against the few a time limit plans;
- ``finalist_halving``: successive halving over the estimate's best against the default finalists.

    OMP_NUM_THREADS=1 python -m experiments.search_value --only sampler_value [--reps 3] [--time-s 900]

Each writes the record of its name (``bench_<strategy>``) under ``benchmarks/results/``.
"""

from __future__ import annotations

from __future__ import annotations
import dataclasses
import gc
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from scipy.stats import kendalltau

from explorer.anytime import anytime_loss, parse_budget
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import Candidate, paper_candidate
from explorer.study.envelope import envelope_steps, spread_along_front
from explorer.study.finalists import choose_finalists
from explorer.study.records import trial_record
from explorer.study.search import SearchRun, search
from explorer.training.deployment import DeploymentData, DeploymentRecipe
from explorer.training.memory import release_host_memory
from explorer.training.train import train

from benchmarks.harness import Bench, Case, rotated, run_suite
from experiments.lib.comparison import (base_config, final_losses, final_recipe, final_recipe_note, fresh_cache,
                                        prepare, run_comparison, run_seeds, run_strategy, SAMPLING_CAP_S,
                                        shared_arguments, STRATEGIES, VAL_FRAMES)


def bench_search_value(argv: Sequence[str] | None = None) -> None:
    """Does the search earn its time? Four ways to spend the same wall time on this machine finding a
    network of the default space (tx2, U(0, 33 ms)), each repetition one seed, the strategies interleaved
    (their order rotates from seed to seed), each given ``--time-s`` T seconds with everything it needs:

    - ``default``: ``explorer search``'s pipeline through its Python API with ``--time-limit T``: the
      supernet trained inside T (a fresh cache folder each run, the generated data linked into it), Optuna's
      TPE sampling its estimates, then the finalists retrained (and, in the time they leave, the envelope's
      networks, which never change the winner); ``make search``'s settings otherwise, but
      no baselines (their retraining is not charged to any strategy: the paper design is retrained below).
    - ``random_sampling``: the same with ``--sampler random`` (uniform sampling, the same supernet recipe).
    - ``random_retrained``: candidates drawn at random from the space (``SearchSpace.random_candidates``),
      no estimate, retrained one after another with the finalists' recipe (``retrain_finalists`` with the
      deadline a search's finalists get) until T is spent; the best measured one is the winner. Their
      steps (``--random-steps``, default 150) are those the search's plan gave its finalists at T = 300 s
      on the slower of the 2-core CPUs measured (``make search``'s 300 shrink to 150 to fit; 200 on a
      faster one).
    - ``proxy``: the search with ``--evaluator proxy``: no supernet, TPE sampling candidates that are each
      trained alone briefly (``--proxy-steps``' 150 at the training size, no tuning; the median pruner
      stops the hopeless ones), then the same finalists. It is successive halving's first rung without
      the estimate: many candidates briefly, the best few with the finalists' recipe.

    Then each seed's winners and the paper design are retrained with one longer recipe (``--final-steps``,
    default 300: twice the finalists', at the training size, then the finalists' tuning steps at the
    deployment size), with that seed, and measured at the deployment size on the first 96 validation
    frames. So are the envelope's dedicated networks (``explorer envelope``'s choice, ``--envelope-networks``
    of them, from the ``default`` strategy's estimates): networks each trained for one path alone (a
    candidate's single-exit twin, or a candidate trained for an earlier path's loss only), spread over the
    budget's range, whose oracle (each budget served by the most accurate one ready by it) is what an
    anytime network of the space can approach. Figures: each winner's anytime loss over the paper design's (``ratio_<strategy>``,
    below 1 is better) and over the envelope's (``envelope_ratio_<strategy>``, 1 is the oracle), a bound
    over the paper design's (``floor_ratio``: the most accurate path of any network measured, as if it were
    ready when the cheapest is; no network of these does better), each strategy's lead in the same seed
    (``lead_<strategy>``: its ratio minus the default's; the seed's data, paper design and retraining noise
    are common to both, so the lead varies less than the ratios do), the strategies' wall times, how many
    candidates each estimated and retrained, and the steps the searches' supernets got.

        OMP_NUM_THREADS=1 python -m experiments.search_value --only search_value [--reps 3] [--time-s 300] [--threads 1]
            [--first-seed 0] [--jobs 1]

    The data is generated once in the usual cache before anything is timed (it is every strategy's).
    PyTorch trains on one thread by default: on two cores that other work keeps busy, two threads wait on
    each other at every kernel (a training step measured 13x slower than on one thread, beside one other
    search), and the strategies' time would go to whoever ran in a quiet spell.
    """
    bench = Bench("bench_search_value", "the search's value: TPE, random sampling, random retraining and proxy training at "
                  "equal time", bench_search_value.__doc__)
    run_comparison(bench, argv, STRATEGIES, time_s=300.0, final_steps=300, random_steps=150,
                   random_steps_why="the searches' finalists' at T = 300 s", envelope_networks=4)


# -- sampler_value ----------------------------------------------------------------------------

SAMPLER_VALUE_STRATEGIES = ("default", "random_sampling")


def bench_sampler_value(argv: Sequence[str] | None = None) -> None:
    """Does TPE earn its place at the length ``make search`` runs? bench_search_value's comparison of the
    default search with the same search sampling at random, at T = 900 s (``make search`` gives the search
    960 s less its setup) rather than 300, where the two were level within the noise: each repetition one
    seed, the two interleaved (their order rotates from seed to seed), each given ``--time-s`` T seconds
    with everything it needs:

    - ``default``: ``explorer search --time-limit T`` as ``make search`` runs it (the supernet trained
      inside T, Optuna's TPE sampling its estimates, the finalists retrained, the envelope's networks in
      the time they leave), no baselines;
    - ``random_sampling``: the same with ``--sampler random`` (uniform sampling of the same supernet
      recipe's estimates).

    Then each seed's two winners, the paper design and the envelope's dedicated networks
    (``--envelope-networks``, default 3) are retrained with a longer recipe (``--final-steps``, default 600:
    twice the finalists' steps, then their tuning) and measured at the deployment size, as in
    bench_search_value, whose figures this bench shares (``ratio_<strategy>``, ``lead_random_sampling``:
    random sampling's ratio minus the default's in the same seed, ``envelope_ratio_<strategy>``,
    ``floor_ratio``, ...).

        OMP_NUM_THREADS=1 python -m experiments.search_value --only sampler_value [--reps 3] [--time-s 900] [--first-seed 0]
    """
    bench = Bench("bench_sampler_value", "TPE against random sampling at make search's length",
                  bench_sampler_value.__doc__)
    run_comparison(bench, argv, SAMPLER_VALUE_STRATEGIES, time_s=900.0, final_steps=600, envelope_networks=3)


# -- search_long ------------------------------------------------------------------------------

SEARCH_LONG_STRATEGIES = ("default", "random_retrained")


def bench_search_long(argv: Sequence[str] | None = None) -> None:
    """Does the search earn its time at the length ``make search`` runs? bench_search_value's comparison of
    the default search with random candidates retrained, at T = 900 s (``make search`` gives the search 960 s
    less its setup) rather than 300: each repetition one seed, the two interleaved (their order rotates
    from seed to seed), each given ``--time-s`` T seconds with everything it needs:

    - ``default``: ``explorer search --time-limit T`` as ``make search`` runs it (the supernet trained
      inside T, TPE sampling its estimates, the finalists retrained, the envelope's networks in the time
      they leave), no baselines;
    - ``random_retrained``: candidates drawn at random from the space, no estimate, retrained one after
      another with the finalists' recipe as ``make search`` asks for it (``--random-steps``, default 300
      steps, then the tuning at 224x224) until T is spent; the best measured one is the winner.

    At 300 s random retraining had the lower median (bench_search_value), with a few more candidates
    retrained than the search's supernet and finalists left room for; here the supernet trains longer and
    the sampling covers more, and random retraining gets about three times the candidates.

    Then each seed's winners, the paper design and the envelope's dedicated networks (``--envelope-networks``,
    default 3) are retrained with a longer recipe (``--final-steps``, default 600: twice the finalists'
    steps, then their tuning) and measured at the deployment size, as in bench_search_value, whose figures
    this bench shares (``ratio_<strategy>``, ``envelope_ratio_<strategy>``, ``floor_ratio``, ...).

        OMP_NUM_THREADS=1 python -m experiments.search_value --only search_long [--reps 3] [--time-s 900]
    """
    bench = Bench("bench_search_long", "the search against random retraining at make search's length",
                  bench_search_long.__doc__)
    run_comparison(bench, argv, SEARCH_LONG_STRATEGIES, time_s=900.0, final_steps=600, random_steps=300,
                   random_steps_why="the finalists' recipe", envelope_networks=3)


# -- envelope ---------------------------------------------------------------------------------

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


def envelope_declare(bench: Bench, final_steps: int) -> None:
    recipe = f"after {final_steps} steps + tuning at 224x224"
    for rule in RULES:
        bench.figure(f"envelope_anytime_{rule}", f"{rule}: the envelope's anytime loss {recipe}", "m", better="lower")
        bench.figure(f"envelope_ratio_{rule}", f"{rule}: the winner's anytime loss / the envelope's", "")
        bench.figure(f"last_ready_{rule}", f"{rule}: when the envelope's last network is ready", "ms")
        bench.figure(f"serving_{rule}", f"{rule}: networks serving some budget", "")
    bench.figure("ratio_default", f"the winner / the paper design, anytime loss {recipe}", "", better="lower")
    bench.figure("supernet_steps", "supernet steps trained inside T", "")


def envelope_one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data) -> None:
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


def bench_envelope(argv: Sequence[str] | None = None) -> None:
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

        OMP_NUM_THREADS=1 python -m experiments.search_value --only envelope [--reps 3] [--time-s 300] [--networks 4]
    """
    bench = Bench("bench_envelope", "the envelope's networks: three ways to choose them from a search's estimates",
                  bench_envelope.__doc__)
    ap = bench.parser()
    shared_arguments(ap, time_s=300.0)
    ap.add_argument("--networks", type=int, default=4, help="dedicated networks each rule chooses (default 4)")
    args = bench.parse_args(ap, argv)
    args.envelope_networks = args.networks    # what run_strategy passes on
    config, data = prepare(args.threads)
    envelope_declare(bench, args.final_steps)
    bench.note(f"cpu, torch threads {args.threads}; a default search of T = {args.time_s:g} s a seed (no baselines); "
               f"{args.networks} networks a rule; {final_recipe_note(config, args.final_steps)}; {config.device}, "
               f"{config.budgets[0]}")
    run_seeds(bench, envelope_one_seed, args, data, "bench-envelope-")
    bench.finish()


# -- finalist_count ---------------------------------------------------------------------------

COUNT_STRATEGIES = ("default", "screened")


SCREENED_FREE = frozenset({"supernet_steps"})


def count_declare(bench: Bench, seconds: float, final_steps: int) -> None:
    for name in COUNT_STRATEGIES:
        bench.figure(f"ratio_{name}", f"{name}: winner / paper design, anytime loss after {final_steps} steps "
                     "+ tuning at 224x224", "", better="lower")
    for name in COUNT_STRATEGIES:
        bench.figure(f"retrained_{name}", f"{name}: finalists retrained inside T = {seconds:g} s", "")
        bench.figure(f"finalist_steps_{name}", f"{name}: each finalist's steps at the training size", "")
        bench.figure(f"supernet_steps_{name}", f"{name}: supernet steps trained inside T", "")
        bench.figure(f"seconds_{name}", f"{name}: wall time", "s")
    bench.figure("paper_anytime", f"paper design: anytime loss after {final_steps} steps + tuning at 224x224", "m",
                 better="lower")


def count_one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data) -> None:
    """The two strategies for ``seed``, in the repetition's order; then their winners and the paper
    design retrained with the longer recipe (a network both strategies chose is trained once)."""
    winners = {}
    for name in rotated(list(COUNT_STRATEGIES), seed):
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
    for name in COUNT_STRATEGIES:
        bench.add(f"ratio_{name}", anytime_loss(*trained[winners[name].key], budget) / paper_loss)


def bench_finalist_count(argv: Sequence[str] | None = None) -> None:
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

        OMP_NUM_THREADS=1 python -m experiments.search_value --only finalist_count [--reps 3] [--time-s 420] [--finalists 5]
    """
    bench = Bench("bench_finalist_count", "more finalists retrained briefly against the few a time limit plans",
                  bench_finalist_count.__doc__)
    ap = bench.parser()
    shared_arguments(ap, time_s=420.0)
    ap.add_argument("--finalists", type=int, default=5, help="the screened strategy's finalists (default 5)")
    ap.add_argument("--steps", type=int, default=150, help="the screened strategy's steps a finalist at the "
                    "training size, before the tuning (default 150)")
    args = bench.parse_args(ap, argv)
    args.envelope_networks = 1    # what run_strategy passes on: the dedicated networks are not retrained here
    config, data = prepare(args.threads)
    count_declare(bench, args.time_s, args.final_steps)
    bench.note(f"cpu, torch threads {args.threads}; T = {args.time_s:g} s a strategy and seed, supernet and data "
               f"loading inside it (a fresh cache each run); no baselines retrained inside T; screened: "
               f"{args.finalists} finalists of {args.steps} steps + tuning; "
               f"{final_recipe_note(config, args.final_steps)}; {config.device}, {config.budgets[0]}")
    run_seeds(bench, count_one_seed, args, data, "bench-finalist-count-")
    bench.finish()


# -- finalist_halving -------------------------------------------------------------------------

HALVING_STRATEGIES = ("default", "halving", "pool_best")


@dataclass
class Retrained:
    """One pool candidate through the finalists' recipe: its estimate, its anytime loss at the rung (the
    recipe's middle, at the training size) and at the end (tuned, at the deployment size), and the
    seconds up to the rung, from there to the end of the training size, and of the tuning."""

    candidate: Candidate
    estimate: float
    rung: float
    final: float
    to_rung_s: float
    after_rung_s: float
    tune_s: float


def path_losses_to_anytime(candidate: Candidate, errors: list[float], config) -> float:
    costs = candidate_cost(candidate, tuple(config.input_size)).path_costs(get_device(config.device), "time")
    return anytime_loss(list(costs), errors, config.budgets[0])


def retrain_with_rung(candidate: Candidate, estimate: float, recipe: DeploymentRecipe, data: DeploymentData,
                      val_small, config) -> Retrained:
    """``candidate`` through ``recipe`` as a finalist is (explorer.training.deployment), its paths also
    measured at the training size half-way through the first phase."""
    rung_step = recipe.train.steps // 2
    torch.manual_seed(recipe.train.seed)
    net = build_network(candidate)
    at_rung: dict = {}

    def report(step, metrics) -> None:
        at_rung["errors"] = [float(x) for x in metrics[config.metric]]
        at_rung["time"] = time.perf_counter()

    started = time.perf_counter()
    train(net, data.train, val_small, dataclasses.replace(recipe.train, eval_every=rung_step), torch.device("cpu"),
          report=report, val_limit=VAL_FRAMES)
    trained = time.perf_counter()
    release_host_memory()
    tuned = train(net, data.deploy_train, data.deploy_val, recipe.tune_config(), torch.device("cpu"),
                  val_limit=VAL_FRAMES)
    final = [float(x) for x in tuned.metrics[config.metric]]
    return Retrained(candidate, estimate, path_losses_to_anytime(candidate, at_rung["errors"], config),
                     path_losses_to_anytime(candidate, final, config), at_rung["time"] - started,
                     trained - at_rung["time"], time.perf_counter() - trained)


def halving_declare(bench: Bench, args) -> None:
    recipe = f"after {args.final_steps} steps + tuning at 224x224"
    for name in HALVING_STRATEGIES:
        bench.figure(f"ratio_{name}", f"{name}: winner / paper design, anytime loss {recipe}", "", better="lower")
    bench.figure("lead_halving", "ratio_halving - ratio_default in the same seed (above 0: the default's winner "
                 "was better)", "", better="higher")
    bench.figure("same_winner", "halving chose the default's winner (1) or another network (0)", "")
    bench.figure("halving_kept_default_winner", "the default's winner among the networks halving kept (1 or 0)", "")
    bench.figure("tau_estimate", f"Kendall tau over the pool of {args.pool}: the estimate against the "
                 "finalists' recipe", "", better="higher")
    bench.figure("tau_rung", f"Kendall tau over the pool of {args.pool}: the rung (half the recipe, training size) "
                 "against the finalists' recipe", "", better="higher")
    bench.figure("seconds_default", f"default: {args.finalists} finalists retrained", "s")
    bench.figure("seconds_halving", f"halving: {args.pool} to the rung, {args.keep} continued and tuned", "s")
    bench.figure("paper_anytime", f"paper design: anytime loss {recipe}", "m", better="lower")


def estimated(seed: int, args, work: Path, data_cache: Path):
    """``make search``'s supernet and sampling for ``seed`` (no finalists, no time limit), in a fresh cache:
    (the study's settings, its pool, the default's finalists), each candidate with its estimate."""
    name = f"halving-{seed}"
    config = base_config(seed, name, finalists=0)
    reports = work / "reports" / name
    with fresh_cache(work / "cache" / name, data_cache):
        study = search(config.resolve(), SearchRun(timeout_s=args.sampling_s, reports=reports)).study

    def chosen(count: int) -> list[tuple[Candidate, float]]:
        return [(Candidate.from_dict(trial_record(t).candidate), t.values[0]) for t in choose_finalists(study, count)]
    pool, finalists = chosen(args.pool), chosen(args.finalists)
    print(f"  seed {seed}: {len(study.trials)} trials; pool {[c.key for c, _ in pool]}", flush=True)
    gc.unfreeze()   # the search froze what it had loaded (explorer.study.search._optimize): let it go
    gc.collect()
    shutil.rmtree(reports, ignore_errors=True)
    return config, pool, finalists


def halving_one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data: DeploymentData) -> None:
    config, pool, finalists = estimated(seed, args, work, data_cache)
    val_small = open_dataset(config.data, "val", config.train_size, train_augment=False)
    recipe = config.finalist_recipe()
    runs: dict[str, Retrained] = {}
    for candidate, estimate in pool + finalists:
        if candidate.key not in runs:
            runs[candidate.key] = r = retrain_with_rung(candidate, estimate, recipe, data, val_small, config)
            print(f"  {candidate.key}: estimate {r.estimate:.4f}, rung {r.rung:.4f}, final {r.final:.4f} "
                  f"({r.to_rung_s:.0f} + {r.after_rung_s:.0f} + {r.tune_s:.0f} s)", flush=True)
    default = [runs[c.key] for c, _ in finalists]
    pooled = [runs[c.key] for c, _ in pool]
    kept = sorted(pooled, key=lambda r: r.rung)[:args.keep]
    winners = {"default": min(default, key=lambda r: r.final), "halving": min(kept, key=lambda r: r.final),
               "pool_best": min(pooled, key=lambda r: r.final)}
    print("  winners: " + ", ".join(f"{k} {w.candidate.key}" for k, w in winners.items()), flush=True)
    bench.add("same_winner", float(winners["halving"] is winners["default"]))
    bench.add("halving_kept_default_winner", float(any(r is winners["default"] for r in kept)))
    bench.add("tau_estimate", kendalltau([r.estimate for r in pooled], [r.final for r in pooled]).statistic)
    bench.add("tau_rung", kendalltau([r.rung for r in pooled], [r.final for r in pooled]).statistic)
    bench.add("seconds_default", sum(r.to_rung_s + r.after_rung_s + r.tune_s for r in default))
    bench.add("seconds_halving", sum(r.to_rung_s for r in pooled) + sum(r.after_rung_s + r.tune_s for r in kept))

    paper, long = paper_candidate(), final_recipe(args.final_steps)
    trained = final_losses([(c.key, c, long) for c in (paper, *(w.candidate for w in winners.values()))], seed, data)
    budget = config.budgets[0]
    loss = {key: anytime_loss(*trained[key], budget) for key in trained}
    bench.add("paper_anytime", loss[paper.key])
    ratio = {name: loss[w.candidate.key] / loss[paper.key] for name, w in winners.items()}
    for name in HALVING_STRATEGIES:
        bench.add(f"ratio_{name}", ratio[name])
    bench.add("lead_halving", ratio["halving"] - ratio["default"])


def bench_finalist_halving(argv: Sequence[str] | None = None) -> None:
    """Successive halving over the estimate's best, against the finalists the study retrains now, at about
    the same retraining time. Each repetition is one seed: ``make search``'s supernet and sampling (no time
    limit, no finalists), then from its estimates

    - ``default``: the finalists ``explorer search`` retrains (``choose_finalists``: the best estimate,
      then the best of each other image encoder; ``--finalists``, default 3), each with the finalists'
      recipe (300 steps at the training size, then the tuning at the deployment size); the best measured one
      is the winner;
    - ``halving``: ``--pool`` candidates chosen the same way (default 6) trained with the same recipe's
      first half (its schedule, stopped at the middle), ranked there by their anytime loss measured at the
      training size (no tuning: that is what makes a rung cheap), the best ``--keep`` (default 2) continued
      to the end of the recipe and tuned, the best measured one the winner. With tuning costing about as much
      as a finalist's training, 6 half-trainings and 2 continuations cost about what 3 finalists do; the
      record holds both strategies' seconds, as measured here, to check it;
    - ``pool_best``: every pool candidate retrained in full, the best measured one: what a perfect first
      rung would keep (twice the default's time; a bound, not a strategy).

    Every pool candidate is trained once, its rung measured on the way (the same schedule and seed as the
    full recipe, so continuing a rung is training in full). Then each seed's winners and the paper design are
    retrained with one longer recipe (``--final-steps``, default 600, then the same tuning), with that
    seed, and measured at the deployment size on the first 96 validation frames, as in bench_search_value.
    Figures: each winner's anytime loss over the paper design's (``ratio_<strategy>``), the halving's
    lead over the default in the same seed, whether both chose the same network, how well the estimate
    and the rung order the pool (Kendall tau against the full recipe's anytime loss), and the seconds each
    strategy's retrainings took.

        OMP_NUM_THREADS=1 python -m experiments.search_value --only finalist_halving [--reps 3] [--pool 6] [--keep 2]
            [--finalists 3] [--final-steps 600] [--first-seed 0]
    """
    bench = Bench("bench_finalist_halving", "successive halving over the estimate's best against the default finalists",
                  bench_finalist_halving.__doc__)
    ap = bench.parser()
    ap.add_argument("--pool", type=int, default=6, help="candidates trained to the rung (default 6)")
    ap.add_argument("--keep", type=int, default=2, help="candidates continued past the rung (default 2)")
    ap.add_argument("--finalists", type=int, default=3, help="the default's finalists (default 3, as make search)")
    ap.add_argument("--final-steps", type=int, default=600, help="steps at the training size of the final "
                    "comparison's recipe, before the tuning (default 600: twice the finalists')")
    ap.add_argument("--sampling-s", type=float, default=SAMPLING_CAP_S,
                    help=f"the search's sampling time (default {SAMPLING_CAP_S:g}, explorer search's)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first repetition's seed (default 0)")
    args = bench.parse_args(ap, argv)
    if not 1 <= args.keep <= args.pool:
        ap.error("--keep must be between 1 and --pool")
    config, data = prepare(args.threads)
    halving_declare(bench, args)
    bench.note(f"cpu, torch threads {args.threads}; make search's supernet ({config.supernet_steps} steps) and "
               f"{args.sampling_s:g} s of sampling a seed; finalists' recipe {config.finalist_steps} steps at "
               f"{config.train_size[0]}x{config.train_size[1]} + {config.tuning_steps} at "
               f"{config.input_size[0]}x{config.input_size[1]}; the rung at step {config.finalist_steps // 2}, "
               f"measured at the training size on {VAL_FRAMES} validation frames; pool {args.pool}, keep {args.keep}, "
               f"default finalists {args.finalists}; seeds {args.first_seed} to {args.first_seed + bench.reps - 1}; "
               f"{final_recipe_note(config, args.final_steps)}; {config.device}, {config.budgets[0]}")
    run_seeds(bench, halving_one_seed, args, data, f"{bench.name}-")
    bench.finish()


CASES = (Case(bench_search_value), Case(bench_sampler_value), Case(bench_search_long), Case(bench_envelope), Case(bench_finalist_count), Case(bench_finalist_halving))

if __name__ == "__main__":
    run_suite(CASES)
