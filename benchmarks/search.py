"""The search's machinery: enumeration, fits, sampling, storage and long studies.

    python -m benchmarks.search --list
    python -m benchmarks.search --only NAME [its options]
"""

from __future__ import annotations

import itertools
import random
import shutil
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import optuna
import pandas as pd
import yaml
from optuna.trial import TrialState, create_trial

import explorer.cost.fit as fit
from explorer.anytime import anytime_loss, parse_budget
from explorer.calibration.calibrate import calibrate, fit_results, read_results
from explorer.cost import candidate_cost, get_device, model_cost
from explorer.cost.workloads import stage_cost
from explorer.space import SearchSpace, paper_candidate
from explorer.study import trial_record
from explorer.study.config import SearchConfig
from explorer.cost.enumerate import candidate_rows, enumerate_space, space_grid, write_enumeration
from explorer.study.objective import FinishedTwins
from explorer.study.sampling import RecentTrialsTPE
from explorer.study.search import make_sampler
from explorer.study.storage import open_storage

from benchmarks.harness import Bench, Case, interleave, rotated, run_suite


# -- enumerate --------------------------------------------------------------------------------

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


def bench_enumerate(argv: Sequence[str] | None = None) -> None:
    """Cost-only enumeration of the whole default space (``explorer enumerate``): every candidate's
    parameters, MACs, per-path latency and energy and the cost side of the anytime loss, written to a CSV
    file, with the Pareto front of the default cost columns over every candidate. The array arithmetic
    (each distinct front and back of the stage list costed once, then summed per candidate with numpy)
    against the per-candidate computation it reproduces exactly (``candidate_rows``), which is too slow
    to run whole: it is timed on the space's first candidates and extrapolated to the whole space.

        python -m benchmarks.search --only enumerate [--reps 3] [--device tx2] [--slice 100000]

    Both start cold in every repetition (the stage cost cache is cleared, so both trace the distinct
    stages they need) and alternate in a rotating order. Before the repetitions, the two are checked to
    give the same rows on the slice's first candidates.
    """
    bench = Bench("bench_enumerate", "Enumerating the whole default space: array arithmetic against per candidate",
                  bench_enumerate.__doc__)
    ap = bench.parser()
    ap.add_argument("--device", default="tx2")
    ap.add_argument("--slice", type=int, default=100_000, help="candidates the per-candidate run costs")
    args = bench.parse_args(ap, argv)
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


# -- fit --------------------------------------------------------------------------------------

class _OneByOne:
    """The reference pricing: ``predict_ms`` for each observation, ``layer_ms`` for each workload."""

    def __init__(self, observations) -> None:
        self.observations = list(observations)

    def predict_ms(self, profile) -> np.ndarray:
        return np.array([fit.predict_ms(profile, o) for o in self.observations])


def _fit(results: dict, batch: type) -> tuple[float, object]:
    """(seconds, profile) of ``fit_results`` with ``batch`` as the module's ObservationBatch."""
    kept, fit.ObservationBatch = fit.ObservationBatch, batch
    try:
        t0 = time.perf_counter()
        prof = fit_results(results)
        return time.perf_counter() - t0, prof
    finally:
        fit.ObservationBatch = kept


def bench_fit(argv: Sequence[str] | None = None) -> None:
    """The host fit (``fit_results``: every layer and stage graph a calibration timed, fp32 and int8, the
    body exponent's grid) with the observations priced as one batch of arrays
    (``explorer.cost.fit.ObservationBatch``) against one Python call per workload, on the same
    measurements: how long a fit takes, since calibration and the study refit often, and how far the two
    fitted profiles' predictions for the paper design lie apart (they should agree to rounding).

        python -m benchmarks.search --only fit [--calibration results.json] [--reps 3]

    Without ``--calibration`` (a calibration's probe results) it first calibrates this machine quickly
    (``explorer calibrate --quick``'s sweep, a few minutes) for measurements to fit. The two pricings
    alternate within each repetition.
    """
    bench = Bench("bench_fit", "Host fit: observations priced as one batch against one by one",
                  bench_fit.__doc__)
    ap = bench.parser()
    ap.add_argument("--calibration", type=Path,
                    help="a calibration's probe results (the probe's results.json)")
    args = bench.parse_args(ap, argv)
    with tempfile.TemporaryDirectory() as tmp:
        path = args.calibration
        if path is None:
            path = Path(tmp) / "calibration.json"
            print("calibrating this machine (quick sweep) for measurements to fit ...", flush=True)
            calibrate(scale=0.35, repeats=5, energy=False, results_out=path)
        results = read_results(path)
    bench.note(f"measurements from {'a quick calibration' if args.calibration is None else args.calibration}")
    bench.figure("batch_s", "fit, observations priced as one batch", "s", "lower")
    bench.figure("one_by_one_s", "fit, observations priced one by one", "s", "lower")
    bench.figure("one_by_one_over_batch", "one by one / batch", "x", "higher")
    bench.figure("path_gap", "largest relative difference of the paper design's path times", "", "lower")
    cost = candidate_cost(paper_candidate(), (224, 224))
    for rep in bench.repetitions():
        got = interleave({"batch": lambda: _fit(results, fit.ObservationBatch),
                          "one_by_one": lambda: _fit(results, _OneByOne)}, rep)
        bench.add("batch_s", got["batch"][0])
        bench.add("one_by_one_s", got["one_by_one"][0])
        bench.add("one_by_one_over_batch", got["one_by_one"][0] / got["batch"][0])
        paths = {k: np.array(cost.path_latency_ms(prof)[1:]) for k, (_, prof) in got.items()}
        bench.add("path_gap", float(np.max(np.abs(paths["batch"] / paths["one_by_one"] - 1))))
    bench.finish()


# -- space ------------------------------------------------------------------------------------

def space_before_widening(wide: SearchSpace) -> SearchSpace:
    with open(wide.source) as f:
        raw = yaml.safe_load(f)
    raw["image_encoder"].pop("exits")
    raw["lidar_encoder"].pop("first")
    raw["exits"].pop("lidar_only")
    return SearchSpace.from_dict(raw, source="before widening")


def timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    got = fn()
    return time.perf_counter() - t0, got


def bench_space(argv: Sequence[str] | None = None) -> None:
    """Cost only (no training): how early the first output comes in the widened default space (exits in
    the image encoder, a learned LiDAR-only path, stage order) against the space before the widening,
    and what it takes to cost each. The widening exists to offer earlier first outputs; the earliest and
    median first-exit times on the chosen device say how much earlier.

        python -m benchmarks.search --only space [--reps 3] [--sample 20000] [--device tx2]

    The space before the widening is enumerated whole; the widened one (over a million candidates) is
    sampled at random (a new seed each repetition), and its earliest first exit is also found exactly (the
    LiDAR-only path, or an encoder exit of the narrowest encoder, whichever comes first). The enumeration
    and the sampling alternate within each repetition.
    """
    bench = Bench("bench_space", "First-exit latency of the widened search space against the space before it",
                  bench_space.__doc__)
    ap = bench.parser()
    ap.add_argument("--sample", type=int, default=20000)
    ap.add_argument("--device", default="tx2")
    args = bench.parse_args(ap, argv)
    wide = SearchSpace.from_yaml("anytime_depth")
    before = space_before_widening(wide)
    dev = get_device(args.device)
    # the exact earliest: every candidate's first path is one of these few stage prefixes
    probes = [c for c in wide.random_candidates(4000, seed=1)
              if c.lidar_exit or (c.encoder_exits and c.width_mult == min(wide.width_mult))]
    exact = min(candidate_cost(c).path_latency_ms(dev)[1] for c in probes)
    lidar = next(c for c in probes if c.lidar_exit)
    bench.note(f"device {dev.name}; {before.size:,} candidates before the widening, {wide.size:,} after; "
               f"{args.sample:,} sampled per repetition; the LiDAR-only path costs "
               f"{candidate_cost(lidar).path_latency_ms(dev)[1]:.3f} ms (inference overhead "
               f"{dev.inference_overhead_ms:.3f} ms included)")
    bench.figure("before_earliest_ms", "earliest first exit before the widening", "ms", "lower")
    bench.figure("before_median_ms", "median first exit before the widening", "ms", "lower")
    bench.figure("widened_earliest_sampled_ms", "earliest first exit, widened (sample)", "ms", "lower")
    bench.figure("widened_median_sampled_ms", "median first exit, widened (sample)", "ms", "lower")
    bench.figure("widened_earliest_exact_ms", "earliest first exit, widened (exact)", "ms", "lower")
    bench.figure("paper_first_ms", "paper design's first exit", "ms", None)
    bench.figure("enumerate_s", "enumerating the space before the widening", "s", "lower")
    bench.figure("sample_s", f"costing {args.sample:,} widened candidates", "s", "lower")
    paper_first = candidate_cost(paper_candidate()).path_latency_ms(dev)[1]
    for rep in bench.repetitions():
        got = interleave({
            "before": lambda: timed(lambda: enumerate_space(before, dev, "time:uniform:33ms")),
            "widened": lambda: timed(lambda: [candidate_cost(c).path_latency_ms(dev)[1]
                                              for c in wide.random_candidates(args.sample, seed=rep)])}, rep)
        (t_old, old), (t_wide, firsts) = got["before"], got["widened"]
        bench.add("before_earliest_ms", old["first_exit_ms"].min())
        bench.add("before_median_ms", old["first_exit_ms"].median())
        bench.add("widened_earliest_sampled_ms", min(firsts))
        bench.add("widened_median_sampled_ms", statistics.median(firsts))
        bench.add("widened_earliest_exact_ms", exact)
        bench.add("paper_first_ms", paper_first)
        bench.add("enumerate_s", t_old)
        bench.add("sample_s", t_wide)
    bench.finish()


# -- sampler ----------------------------------------------------------------------------------

OPTIONS = dict(n_startup_trials=8, multivariate=True, group=True)


TAIL = 500


def _sampler(kind: str, seed: int) -> optuna.samplers.BaseSampler:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if kind == "tpe":
            return optuna.samplers.TPESampler(seed=seed, constant_liar=False, **OPTIONS)
        return RecentTrialsTPE(seed=seed, **OPTIONS)


def run(kind: str, trials: int, seed: int) -> tuple[float, float]:
    """(CPU ms an ask over the last TAIL trials, best loss) of one study."""
    space, tx2, budget = SearchSpace.from_yaml("anytime_depth"), get_device("tx2"), parse_budget("time:uniform:33ms")
    study = optuna.create_study(sampler=_sampler(kind, seed))
    asks = []
    for _ in range(trials):
        t0 = time.process_time()
        trial = study.ask()
        candidate = space.sample(trial)      # TPE samples the parameters as they are asked for
        asks.append(time.process_time() - t0)
        cost = model_cost(candidate, (224, 224))
        errors = [0.4 + 1.0 / (1.0 + macs / 1e8) for _, macs in cost.path_params_macs()]
        study.tell(trial, anytime_loss(cost.path_costs(tx2, "time"), errors, budget))
    return 1000 * sum(asks[-TAIL:]) / TAIL, study.best_value


def bench_sampler(argv: Sequence[str] | None = None) -> None:
    """The search's sampler on a long study: what an ask costs after thousands of trials, and what it
    finds. Optuna's TPE (as a search sets it up: multivariate, grouped) reads every finished trial at
    every ask; the search's sampler (:class:`explorer.study.sampling.RecentTrialsTPE`) reads the best
    and the latest ones. Both run ``--trials`` trials of the default space on a synthetic anytime
    objective (each path's error falls with its MACs, the paths are costed on the TX2, budget
    U(0, 33 ms)), so that no network is trained and only the sampler differs.

        python -m benchmarks.search --only sampler [--reps 3] [--trials 1500]

    Each repetition runs both samplers, in an order that rotates, with the repetition's seed; the ask
    time is the CPU time of the last 500 trials' asks, the quality the best anytime loss found.
    """
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    bench = Bench("bench_sampler", "The sampler on a long study: ask cost and the best found",
                  bench_sampler.__doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=1500, help="trials per study (the ask time is over the last 500)")
    args = bench.parse_args(ap, argv)
    bench.note(f"{args.trials} trials a study; ask time over the last {TAIL}")
    for kind, label in (("tpe", "Optuna's TPE, every trial"), ("recent", "the search's sampler, best and latest")):
        bench.figure(f"{kind}_ask_ms", f"{label}: CPU per ask", "ms", "lower")
        bench.figure(f"{kind}_best", f"{label}: best anytime loss found", "", "lower")
    bench.figure("ask_speedup", "TPE's ask / the search sampler's ask", "x", "higher")
    for rep in bench.repetitions():
        got = interleave({"tpe": lambda: run("tpe", args.trials, rep),
                          "recent": lambda: run("recent", args.trials, rep)}, rep)
        for kind in ("tpe", "recent"):
            bench.add(f"{kind}_ask_ms", got[kind][0])
            bench.add(f"{kind}_best", got[kind][1])
        bench.add("ask_speedup", got["tpe"][0] / got["recent"][0])
    bench.finish()


# -- long_study -------------------------------------------------------------------------------

ASKS = 20


def finished_trials(space: SearchSpace, n: int, seed: int) -> list:
    """``n`` complete trials of ``space`` with random parameters and a search's user attributes."""
    source = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=seed))
    rng = random.Random(seed)
    made = []
    for _ in range(n):
        trial = source.ask()
        candidate = space.sample(trial)
        source.tell(trial, rng.random())
        frozen = source._storage.get_trial(trial._trial_id)
        made.append(create_trial(state=TrialState.COMPLETE, params=frozen.params, distributions=frozen.distributions,
                                 values=frozen.values, user_attrs={
                                     "candidate": candidate.to_dict(), "candidate_key": candidate.key,
                                     "path_metrics": [{"rmse": rng.random()} for _ in range(6)],
                                     "latency_ms": [rng.random() for _ in range(6)]}))
    return made


def walk(study: optuna.Study, key: str):
    """The finished twin of ``key`` by walking every complete trial (the comparison)."""
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        if trial_record(t).candidate_key == key and not trial_record(t).baseline and \
                trial_record(t).path_metrics is not None and not trial_record(t).is_retrained:
            return t
    return None


def asks(study: optuna.Study, space: SearchSpace, twins: FinishedTwins, rep: int) -> dict[str, float]:
    """Median ms per trial of the sampler's ask, the indexed twin look-up and the walk."""
    times: dict[str, list[float]] = {"ask": [], "index": [], "walk": []}
    for i in range(ASKS):
        started = time.perf_counter()
        trial = study.ask()
        candidate = space.sample(trial)
        times["ask"].append(time.perf_counter() - started)

        def timed(fn):
            started = time.perf_counter()
            got = fn()
            return time.perf_counter() - started, got
        got = interleave({"index": lambda: timed(lambda: twins.find(study, candidate.key)),
                          "walk": lambda: timed(lambda: walk(study, candidate.key))}, rep * ASKS + i)
        if len({getattr(got[k][1], "number", None) for k in ("index", "walk")}) > 1:
            raise AssertionError("the index and the walk found different twins")
        for name in ("index", "walk"):
            times[name].append(got[name][0])
        study.tell(trial, 1.0)
    return {name: 1000 * statistics.median(v) for name, v in times.items()}


def bench_long_study(argv: Sequence[str] | None = None) -> None:
    """A search's bookkeeping once its study holds thousands of trials, as a GPU's search does after ten
    minutes: the sampler's ask (TPE over the best and latest trials, and the new trials found) and the
    look-up of a finished twin (a candidate the sampler proposes again), per trial. The twin is looked up
    in the search's index of complete trials, kept up to date with the new ones, and, for comparison, by
    walking every complete trial, as a plain scan does.

        python -m benchmarks.search --only long_study [--reps 3] [--trials 10000]

    The study is a journal file filled with --trials finished trials of the default space (random
    parameters, the user attributes a search stores), as a search leaves it; no network is trained.
    Each repetition asks 20 trials at 1,000 finished trials and at --trials, and times each twin look-up
    both ways in turn; the figures are medians over a repetition's trials.
    """
    bench = Bench("bench_long_study", "a long study's bookkeeping: the sampler's ask and the twin look-up",
                  bench_long_study.__doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=10_000, help="finished trials in the study (default 10000)")
    args = bench.parse_args(ap, argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
    space = SearchSpace.from_yaml("anytime_depth")
    sizes = (1000, args.trials)
    for n in sizes:
        bench.figure(f"ask_ms_{n}", f"sampler's ask at {n} finished trials", "ms", "lower")
    bench.figure("twin_index_ms", f"twin look-up in the index, {args.trials} trials", "ms", "lower")
    bench.figure("twin_walk_ms", f"twin look-up walking every trial, {args.trials} trials", "ms", "lower")
    bench.figure("twin_speedup", "walk / index", "x", "higher")
    bench.note(f"journal file study of {args.trials} finished trials of the default space; {ASKS} asks a size")
    made = finished_trials(space, args.trials, seed=0)
    for rep in bench.repetitions():
        with tempfile.TemporaryDirectory() as tmp:
            storage = open_storage(None, f"long-{rep}", 1, Path(tmp))
            study = optuna.create_study(study_name=f"long-{rep}", storage=storage, sampler=RecentTrialsTPE(
                seed=rep, n_startup_trials=8, multivariate=True, group=True))
            twins = FinishedTwins()
            for n in sizes:
                have = len(study.get_trials(deepcopy=False))
                study.add_trials(made[have:n])
                got = asks(study, space, twins, rep)
                bench.add(f"ask_ms_{n}", got["ask"])
            bench.add("twin_index_ms", got["index"])
            bench.add("twin_walk_ms", got["walk"])
            bench.add("twin_speedup", got["walk"] / got["index"])
    bench.finish()


# -- search_overhead --------------------------------------------------------------------------

STORAGES = ("journal", "journal_each", "sqlite_synced", "sqlite_wal", "memory")


def _storage(kind: str, folder: Path):
    if kind == "memory":
        return optuna.storages.InMemoryStorage()
    if kind == "sqlite_synced":
        return optuna.storages.RDBStorage(f"sqlite:///{folder / 'study.db'}")
    if kind == "journal":
        return open_storage(None, "bench", reports=folder.parent)
    if kind == "journal_each":
        from optuna.storages.journal import JournalFileBackend
        return optuna.storages.JournalStorage(JournalFileBackend(str(folder / "journal.log")))
    return open_storage(f"sqlite:///{folder / 'study.db'}", "bench")


def _per_trial(kind: str, trials: int, config: SearchConfig) -> tuple[float, float]:
    """(wall ms, CPU ms) a trial of ``trials`` with the storage ``kind``."""
    space, device = SearchSpace.from_yaml(config.space), get_device(config.device)

    def objective(trial: optuna.Trial) -> float:
        cand = space.sample(trial)
        cost = model_cost(cand, config.input_size)
        latency = cost.path_latency_ms(device)
        trial.study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))  # the duplicate check
        trial.set_user_attr("candidate", cand.to_dict())
        for name in ("candidate_key", "params", "macs", "latency_ms", "energy_j", "workloads", "path_metrics",
                     "evaluator", "losses"):
            trial.set_user_attr(name, latency)   # as many attributes as a search stores, of a similar size
        return latency[-1]

    root = Path(tempfile.mkdtemp())
    try:
        folder = root / "bench"
        folder.mkdir()
        study = optuna.create_study(storage=_storage(kind, folder), study_name="bench", sampler=make_sampler(config))
        wall, cpu = time.perf_counter(), time.process_time()
        study.optimize(objective, n_trials=trials)
        return 1000 * (time.perf_counter() - wall) / trials, 1000 * (time.process_time() - cpu) / trials
    finally:
        shutil.rmtree(root, ignore_errors=True)


def bench_search_overhead(argv: Sequence[str] | None = None) -> None:
    """A search's bookkeeping per trial, without the evaluator: the sampler (TPE as a search sets it up),
    sampling a candidate of the default space, costing its paths on the TX2 profile, and the storage
    writes of its parameters and attributes, and the reads the sampler makes. Five storages: the journal
    file a search on this machine keeps its study in (:func:`explorer.study.storage.open_storage`, synced
    to the disk at trial state changes), the same journal as Optuna's file backend writes it (synced
    after every line),
    SQLite as Optuna opens it (a rollback journal, synced at every commit), SQLite as ``explorer search``
    opens it for ``--storage sqlite:///...`` (a write-ahead log, synced at checkpoints), and memory (what
    the sampler and the costing take alone).

        python -m benchmarks.search --only search_overhead [--reps 3] [--trials 150]

    Each repetition runs ``--trials`` trials on a fresh study with each storage, in an order that rotates,
    and records wall and CPU milliseconds a trial. Evaluating a candidate with the supernet takes about
    0.1 s on a GPU and 0.3-1 s on two CPU cores; what is here is what comes on top.
    """
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    bench = Bench("bench_search_overhead", "A search's bookkeeping per trial: sampler, costing and storage",
                  bench_search_overhead.__doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=150, help="trials per storage and repetition")
    args = bench.parse_args(ap, argv)
    config = SearchConfig(study="bench")
    labels = {"journal": "journal file (the default)", "journal_each": "journal file, synced after every line",
              "sqlite_synced": "SQLite, synced at every commit", "sqlite_wal": "SQLite, write-ahead log",
              "memory": "in memory (sampler and costing alone)"}
    for kind in STORAGES:
        bench.figure(f"{kind}_ms", f"{labels[kind]}, wall", "ms", "lower")
        bench.figure(f"{kind}_cpu_ms", f"{labels[kind]}, CPU", "ms", "lower")
    bench.figure("synced_over_wal", "synced / write-ahead log, wall", "x", "higher")
    bench.figure("wal_over_journal", "SQLite write-ahead log / journal file, wall", "x", "higher")
    bench.figure("each_over_journal", "journal synced every line / at state changes, wall", "x", "higher")
    for rep in bench.repetitions():
        got = {kind: _per_trial(kind, args.trials, config) for kind in rotated(STORAGES, rep)}
        for kind in STORAGES:
            bench.add(f"{kind}_ms", got[kind][0])
            bench.add(f"{kind}_cpu_ms", got[kind][1])
        bench.add("synced_over_wal", got["sqlite_synced"][0] / got["sqlite_wal"][0])
        bench.add("wal_over_journal", got["sqlite_wal"][0] / got["journal"][0])
        bench.add("each_over_journal", got["journal_each"][0] / got["journal"][0])
    bench.finish()


CASES = (Case(bench_enumerate), Case(bench_fit), Case(bench_space), Case(bench_sampler), Case(bench_long_study),
         Case(bench_search_overhead))

if __name__ == "__main__":
    run_suite(CASES)
