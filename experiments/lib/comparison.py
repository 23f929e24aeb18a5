"""The machinery of the search-value experiment (``experiments.search_value``): ways to spend the same
wall time finding a network of the default space (``STRATEGIES``), each seed's winners retrained with
one longer recipe and measured at the deployment size, beside the paper design and the envelope's
dedicated networks; the figures every strategy of that experiment shares."""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import gc
import multiprocessing
import os
import shutil
import tempfile
import time
from pathlib import Path

import optuna
import torch

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.data.synthetic import cache_dir
from explorer.model import build_network
from explorer.space import Candidate, paper_candidate
from explorer.study.config import SearchConfig, study_context
from explorer.study.envelope import envelope_steps, estimated_networks, spread_along_front
from explorer.study.finalists import estimate_trials, finalist_trials, retrain_finalists
from explorer.study.planning import RESERVE_S, TimeLimit
from explorer.study.records import record_values, study_record, trial_record
from explorer.study.results import winner
from explorer.study.search import SearchRun, search
from explorer.supernet import read_supernet
from explorer.training.deployment import DeploymentData, DeploymentRecipe, train_for_deployment

from benchmarks.harness import Bench, rotated

STRATEGIES = ("default", "random_sampling", "random_retrained", "proxy")
#: the strategies that train no supernet
NO_SUPERNET = ("random_retrained", "proxy")
VAL_FRAMES = 96
#: `explorer search`'s own cap on sampling (its --timeout default); a time limit shrinks it further
SAMPLING_CAP_S = 180.0
#: random candidates put up for retraining: more than T can hold, the deadline decides how many are
RANDOM_POOL = 60


def base_config(seed: int, study: str, **changes) -> SearchConfig:
    """``make search``'s study (tx2, the default space and budget, 3 finalists of 300 steps, a 600-step
    supernet, all left to the time limit) without baselines, for ``seed``."""
    return SearchConfig(study=study, seed=seed, baselines=(), keep_weights=False, **changes)


@contextlib.contextmanager
def fresh_cache(folder: Path, data_cache: Path):
    """``ANYTIME_EXPLORER_CACHE`` set to the new ``folder``, the generated data linked into it: no
    supernet is found there, so a strategy that needs one trains it inside its own time."""
    folder.mkdir(parents=True)
    for data in data_cache.glob("synthetic-*.h5"):
        (folder / data.name).symlink_to(data)
    before = os.environ.get("ANYTIME_EXPLORER_CACHE")
    os.environ["ANYTIME_EXPLORER_CACHE"] = str(folder)
    try:
        yield folder
    finally:
        if before is None:
            os.environ.pop("ANYTIME_EXPLORER_CACHE", None)
        else:
            os.environ["ANYTIME_EXPLORER_CACHE"] = before
        shutil.rmtree(folder, ignore_errors=True)


def _candidate(trial: optuna.trial.FrozenTrial | None) -> Candidate:
    if trial is None:
        raise SystemExit("a strategy ended without a winner: give it a longer --time-s")
    return Candidate.from_dict(trial_record(trial).candidate)


def estimated_scan_error(study: optuna.Study, metric: str) -> float | None:
    """The scan's error (path 0: no network, the same for every candidate) as the search measured it."""
    for t in estimate_trials(study):
        errors = trial_record(t).losses_of(metric)
        if errors:
            return errors[0]
    return None


def searched(config: SearchConfig, seconds: float, reports: Path, envelope_networks: int,
             free: frozenset[str] = TimeLimit.free) -> tuple[Candidate, dict]:
    """``explorer search --time-limit`` with ``config`` (``free``: the settings left to the plan, as a
    user who sets none): (its winner, what the run did, with the dedicated networks ``explorer envelope``
    would choose from its estimates)."""
    limit = TimeLimit(seconds, time.time(), free)
    outcome = search(config.resolve(), SearchRun(timeout_s=SAMPLING_CAP_S, reports=reports, time_limit=limit))
    study, plan = outcome.study, outcome.plan
    supernet = study_record(study).supernet
    state = read_supernet(Path(supernet)) if supernet else {}
    retrained = finalist_trials(study)
    print(f"    {plan.describe() if plan else 'no plan'}; supernet trained {state.get('step', 0)} steps", flush=True)
    for change in plan.changes if plan else ():
        print(f"      {change}", flush=True)
    context = study_context(study)
    points = estimated_networks(study, context)   # what explorer envelope chooses from
    return _candidate(winner(study)), {"estimated": len(estimate_trials(study)), "retrained": len(retrained),
                                       "finalist_steps": plan.finalist_steps if plan else config.finalist_steps,
                                       "supernet_steps": state.get("step", 0), "estimated_networks": points,
                                       "scan_error": estimated_scan_error(study, config.metric),
                                       "dedicated": spread_along_front(points, envelope_networks)}


def random_retrained(config: SearchConfig, seconds: float, reports: Path) -> tuple[Candidate, dict]:
    """Random candidates retrained with the finalists' recipe until ``seconds`` are spent (the best
    measured one wins): a study holding them as estimate trials (in the order drawn, no estimate), its
    finalists retrained with the deadline a search gives its own."""
    started = time.time()
    context = config.resolve()
    drawn = context.space.random_candidates(RANDOM_POOL, seed=config.seed)
    study = optuna.create_study(study_name=config.study, storage=optuna.storages.InMemoryStorage())
    for rank, candidate in enumerate(drawn):   # the value orders them; choose_finalists spreads encoders
        study.add_trial(optuna.trial.create_trial(values=[float(rank)], user_attrs=record_values(
            candidate=candidate.to_dict(), candidate_key=candidate.key, path_metrics=[], workloads={})))
    context = context.with_config(dataclasses.replace(config, finalists=len(drawn)))
    done = retrain_finalists(study, context, reports, deadline=started + seconds - RESERVE_S)
    best = min(done, key=lambda t: t.values[0], default=None)
    return _candidate(best), {"estimated": 0, "retrained": len(done)}


def run_strategy(name: str, seed: int, args, work: Path, data_cache: Path, changes: dict | None = None,
                 free: frozenset[str] = TimeLimit.free) -> tuple[Candidate, dict]:
    """One strategy's run for ``seed`` in ``args.time_s`` seconds, in a cache and reports folder of its
    own, with the settings ``changes`` of the study (``free``: those left to the plan): (its winner, what
    it did, with its wall time)."""
    study, seconds = f"value-{name}-{seed}", args.time_s
    reports = work / "reports" / study
    config = base_config(seed, study, sampler="random" if name == "random_sampling" else "tpe",
                         evaluator="proxy" if name == "proxy" else "auto", **(changes or {}))
    if name == "random_retrained":
        config = dataclasses.replace(config, finalist_steps=args.random_steps)
    print(f"  {name} (seed {seed}):", flush=True)
    with fresh_cache(work / "cache" / study, data_cache):
        t0 = time.perf_counter()
        if name == "random_retrained":
            best, info = random_retrained(config, seconds, reports)
        else:
            best, info = searched(config, seconds, reports, args.envelope_networks, free)
        info["seconds"] = time.perf_counter() - t0
    gc.unfreeze()   # the search froze what it had loaded (explorer.study.search._optimize): let it go
    gc.collect()
    shutil.rmtree(reports, ignore_errors=True)
    print(f"    winner {best.key} after {info['seconds']:.0f} s ({info['estimated']} estimated, "
          f"{info['retrained']} retrained)", flush=True)
    return best, info


def final_recipe(steps: int) -> DeploymentRecipe:
    """The longer recipe every winner and the paper design are compared with: the finalists' recipe with
    ``steps`` at the training size, then the same tuning at the deployment size."""
    config = base_config(0, "final", finalist_steps=steps)
    return config.finalist_recipe()


def deployment_data(config: SearchConfig) -> DeploymentData:
    return DeploymentData(open_dataset(config.data, "train", config.train_size, seed=config.seed),
                          open_dataset(config.data, "train", config.input_size, seed=config.seed),
                          open_dataset(config.data, "val", config.input_size, train_augment=False))


def measured(candidate: Candidate, seed: int, recipe: DeploymentRecipe,
             data: DeploymentData) -> tuple[list[float], list[float]]:
    """``candidate`` trained with ``recipe`` and ``seed``: (each path's cost on tx2, its RMSE at the
    deployment size on the first VAL_FRAMES validation frames)."""
    config = base_config(seed, "final")
    torch.manual_seed(seed)
    net = build_network(candidate)
    recipe = dataclasses.replace(recipe, train=dataclasses.replace(recipe.train, seed=seed))
    result = train_for_deployment(net, data, recipe, torch.device("cpu"), val_limit=VAL_FRAMES)
    rmse = [float(x) for x in result.metrics[config.metric]]
    cost = candidate_cost(candidate, tuple(config.input_size)).path_costs(get_device(config.device), "time")
    return list(cost), rmse


def declare(bench: Bench, seconds: float, final_steps: int, strategies: tuple[str, ...] = STRATEGIES) -> None:
    recipe = f"after {final_steps} steps + tuning at 224x224"
    for name in strategies:
        bench.figure(f"ratio_{name}", f"{name}: winner / paper design, anytime loss {recipe}", "", better="lower")
    for name in (*strategies, "paper"):
        bench.figure(f"envelope_ratio_{name}", f"{name}: anytime loss / the envelope's (dedicated networks), "
                     f"{recipe}", "", better="lower")
    for name in strategies:
        if name != "default":
            bench.figure(f"lead_{name}", f"ratio_{name} - ratio_default in the same seed (above 0: the default's "
                         "winner was better)", "", better="higher")
    for name in strategies:
        bench.figure(f"seconds_{name}", f"{name}: wall time (T = {seconds:g} s)", "s")
        bench.figure(f"estimated_{name}", f"{name}: candidates estimated", "")
        bench.figure(f"retrained_{name}", f"{name}: candidates retrained", "")
        if name not in NO_SUPERNET:
            bench.figure(f"supernet_steps_{name}", f"{name}: supernet steps trained inside T", "")
    bench.figure("paper_anytime", f"paper design: anytime loss {recipe}", "m", better="lower")
    bench.figure("envelope_anytime", f"envelope of dedicated networks: anytime loss {recipe}", "m", better="lower")
    bench.figure("envelope_networks", "dedicated networks on the envelope (serving some budget)", "")
    bench.figure("floor_ratio", f"bound: the most accurate path measured, as if ready when the cheapest is, "
                 f"/ paper design, anytime loss {recipe}", "", better="lower")


def final_losses(networks: list[tuple[str, Candidate, DeploymentRecipe]], seed: int,
                 data: DeploymentData) -> dict[str, tuple[list[float], list[float]]]:
    """Each distinct network (key, candidate, recipe) trained: its key -> (path costs, path RMSEs)."""
    done: dict[str, tuple[list[float], list[float]]] = {}
    for key, candidate, recipe in networks:
        if key not in done:
            t0 = time.perf_counter()
            done[key] = measured(candidate, seed, recipe, data)
            print(f"  final: {key} RMSE by path {[round(x, 4) for x in done[key][1]]} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return done


def floor_steps(trained: dict[str, tuple[list[float], list[float]]]) -> tuple[list[float], list[float]]:
    """A bound on what any network of these could do: the lowest error of any path (past the scan, path
    0) of any network ``trained``, as if it were ready when the cheapest such path is. An anytime network
    whose paths are none more accurate than the best measured and none faster than the fastest does no
    better: a lower anytime loss needs a path better than any measured."""
    paths = [(c, e) for costs, errors in trained.values() for c, e in zip(costs[1:], errors[1:])]
    scan = next(iter(trained.values()))[1][0]
    return [0.0, min(c for c, _ in paths)], [scan, min(e for _, e in paths)]


def one_seed(bench: Bench, seed: int, args, work: Path, data_cache: Path, data: DeploymentData,
             strategies: tuple[str, ...] = STRATEGIES) -> None:
    """The ``strategies`` (``default`` among them) for ``seed``, in the repetition's order; then their winners, the paper design
    and the envelope's dedicated networks (each trained for its path alone) retrained with the longer
    recipe (a network two strategies share is trained once)."""
    winners, dedicated = {}, []
    for name in rotated(list(strategies), seed):
        winners[name], info = run_strategy(name, seed, args, work, data_cache)
        for figure in ("seconds", "estimated", "retrained", "supernet_steps"):
            if figure in info and not (figure == "supernet_steps" and name in NO_SUPERNET):
                bench.add(f"{figure}_{name}", info[figure])
        if name == "default":
            dedicated = info["dedicated"]
    print(f"  envelope: {len(dedicated)} dedicated networks from the default's estimates", flush=True)
    paper, recipe = paper_candidate(), final_recipe(args.final_steps)
    trained = final_losses([(c.key, c, recipe) for c in (paper, *winners.values())]
                           + [(n.key, n.candidate, n.recipe(recipe)) for n in dedicated], seed, data)
    budget = base_config(seed, "final").budgets[0]
    loss = {c.key: anytime_loss(*trained[c.key], budget) for c in (paper, *winners.values())}
    scan = trained[paper.key][1][0]    # path 0, the interpolated scan: the same frames, the same for all
    steps = envelope_steps(scan, [(trained[n.key][0][n.path], trained[n.key][1][n.path]) for n in dedicated])
    envelope = anytime_loss(*steps, budget)
    print(f"  envelope: anytime loss {envelope:.4f} from steps {[(round(c, 1), round(e, 4)) for c, e in zip(*steps)]}",
          flush=True)
    bench.add("paper_anytime", loss[paper.key])
    bench.add("envelope_anytime", envelope)
    bench.add("envelope_networks", len(steps[0]) - 1)
    bench.add("envelope_ratio_paper", loss[paper.key] / envelope)
    floor = floor_steps(trained)
    print(f"  bound: the most accurate path {floor[1][1]:.4f} as if ready at {floor[0][1]:.1f} ms", flush=True)
    bench.add("floor_ratio", anytime_loss(*floor, budget) / loss[paper.key])
    for name in strategies:
        bench.add(f"ratio_{name}", loss[winners[name].key] / loss[paper.key])
        bench.add(f"envelope_ratio_{name}", loss[winners[name].key] / envelope)
    for name in strategies:   # paired: the seed's data, paper design and retraining noise cancel out
        if name != "default":
            bench.add(f"lead_{name}", (loss[winners[name].key] - loss[winners["default"].key]) / loss[paper.key])


def prepare(threads: int) -> tuple[SearchConfig, DeploymentData]:
    """PyTorch on ``threads`` threads, Optuna quiet, and the data generated before anything is timed (it
    is every strategy's): (the default study's settings, its deployment data)."""
    torch.set_num_threads(threads)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    config = base_config(0, "data")
    data = deployment_data(config)
    open_dataset(config.data, "val", config.train_size, train_augment=False)
    return config, data


def final_recipe_note(config: SearchConfig, final_steps: int) -> str:
    return (f"final recipe {final_steps} steps at {config.train_size[0]}x{config.train_size[1]} + "
            f"{final_recipe(final_steps).tune_steps} at {config.input_size[0]}x{config.input_size[1]}, "
            f"measured on {VAL_FRAMES} "
            "validation frames")


class SeedValues:
    """What one seed adds to the bench in a worker process: the figures' values in order."""

    def __init__(self) -> None:
        self.values: list[tuple[str, float]] = []

    def add(self, name: str, value: float) -> float:
        self.values.append((name, float(value)))
        return float(value)


@functools.cache
def _worker_data(threads: int) -> DeploymentData:
    """A worker process's deployment data, opened once a process (PyTorch set to ``threads`` threads)."""
    return prepare(threads)[1]


def _seed_in_worker(one_seed, seed: int, args, work: Path, data_cache: Path) -> list[tuple[str, float]]:
    """``one_seed`` for ``seed`` in a worker process: the values it added."""
    values = SeedValues()
    one_seed(values, seed, args, work, data_cache, _worker_data(args.threads))
    return values.values


def run_seeds(bench: Bench, one_seed, args, data: DeploymentData, prefix: str) -> None:
    """``one_seed(bench, seed, args, work, data_cache, data)`` for each repetition (seeds ``args.first_seed``
    on), in a work folder of its own that is removed after. With ``--jobs`` N above 1, N seeds run at once,
    each in a process of its own (every run then has another beside it, as on a busy machine); their
    values join the record in the seeds' order."""
    work = Path(tempfile.mkdtemp(prefix=prefix))
    jobs = getattr(args, "jobs", 1)
    try:
        if jobs <= 1:
            for rep in bench.repetitions():
                one_seed(bench, args.first_seed + rep, args, work, cache_dir(), data)
            return
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(jobs, mp_context=context) as pool:
            futures = [pool.submit(_seed_in_worker, one_seed, args.first_seed + rep, args, work, cache_dir())
                       for rep in range(bench.reps)]
            for rep in bench.repetitions():
                for name, value in futures[rep].result():
                    bench.add(name, value)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def shared_arguments(ap, time_s: float, final_steps: int = 300) -> None:
    """The options every bench built on this one takes: the wall time T of each run, the final
    recipe's steps (more than the plan gives the finalists at T) and PyTorch's threads."""
    ap.add_argument("--time-s", type=float, default=time_s, help=f"wall time T of each run (default {time_s:g})")
    ap.add_argument("--final-steps", type=int, default=final_steps, help="steps at the training size of the "
                    f"final comparison's recipe, before the tuning (default {final_steps}: more than the plan "
                    f"gives the finalists at T = {time_s:g} s)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first repetition's seed, the next ones "
                    "following it (default 0): another run's seeds add independent evidence to a record's")
    ap.add_argument("--jobs", type=int, default=1, help="seeds run at once, one process each (default 1; "
                    "2 on two cores with --threads 1: each run then has one other beside it)")


def random_note(args) -> str:
    steps = getattr(args, "random_steps", None)
    return "" if steps is None else f"random candidates retrained {steps} steps + tuning; "


def run_comparison(bench: Bench, argv, strategies: tuple[str, ...], time_s: float, final_steps: int,
                   envelope_networks: int, random_steps: int = 0, random_steps_why: str = "") -> None:
    """The whole run of a bench comparing ``strategies`` (this one's or a subset): its options and
    their defaults, the data, each seed's strategies and final retrainings, the record."""
    ap = bench.parser()
    shared_arguments(ap, time_s=time_s, final_steps=final_steps)
    if "random_retrained" in strategies:
        ap.add_argument("--random-steps", type=int, default=random_steps, help="steps at the training size of "
                        f"each random candidate's retraining, before the tuning (default {random_steps}: "
                        f"{random_steps_why})")
    ap.add_argument("--envelope-networks", type=int, default=envelope_networks, help="dedicated networks of the "
                    f"envelope, as `explorer envelope --networks` (default {envelope_networks})")
    args = bench.parse_args(ap, argv)
    config, data = prepare(args.threads)
    declare(bench, args.time_s, args.final_steps, strategies)
    bench.note(f"cpu, torch threads {args.threads}; T = {args.time_s:g} s a strategy and seed, supernet and data "
               f"loading inside it (a fresh cache each run); no baselines retrained inside T; "
               f"{random_note(args)}{args.envelope_networks} dedicated networks; "
               f"seeds {args.first_seed} to {args.first_seed + bench.reps - 1}, {args.jobs} at once; "
               f"{final_recipe_note(config, args.final_steps)}; {config.device}, {config.budgets[0]}")
    run_seeds(bench, functools.partial(one_seed, strategies=strategies), args, data, f"{bench.name}-")
    bench.finish()
