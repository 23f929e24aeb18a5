"""A search's bookkeeping once its study holds thousands of trials, as a GPU's search does after ten
minutes: the sampler's ask (TPE over the best and latest trials, and the new trials found) and the
look-up of a finished twin (a candidate the sampler proposes again), per trial. The twin is looked up
in the search's index of complete trials, kept up to date with the new ones, and, for comparison, by
walking every complete trial, as a plain scan does.

    python benchmarks/bench_long_study.py [--reps 3] [--trials 10000]

The study is a journal file filled with --trials finished trials of the default space (random
parameters, the user attributes a search stores), as a search leaves it; no network is trained.
Each repetition asks 20 trials at 1,000 finished trials and at --trials, and times each twin look-up
both ways in turn; the figures are medians over a repetition's trials.
"""

import random
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import optuna
from optuna.trial import TrialState, create_trial

from explorer.space import SearchSpace
from explorer.study.objective import FinishedTwins
from explorer.study.sampling import RecentTrialsTPE
from explorer.study.storage import open_storage

from harness import Bench, interleave
from explorer.study import trial_record

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


def main() -> None:
    bench = Bench(__file__, "a long study's bookkeeping: the sampler's ask and the twin look-up", __doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=10_000, help="finished trials in the study (default 10000)")
    args = bench.parse_args(ap)
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


if __name__ == "__main__":
    main()
