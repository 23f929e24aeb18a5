"""The search's sampler on a long study: what an ask costs after thousands of trials, and what it
finds. Optuna's TPE (as a search sets it up: multivariate, grouped) reads every finished trial at
every ask; the search's sampler (:class:`explorer.study.sampling.RecentTrialsTPE`) reads the best
and the latest ones. Both run ``--trials`` trials of the default space on a synthetic anytime
objective (each path's error falls with its MACs, the paths are costed on the TX2, budget
U(0, 33 ms)), so that no network is trained and only the sampler differs.

    python benchmarks/bench_sampler.py [--reps 3] [--trials 1500]

Each repetition runs both samplers, in an order that rotates, with the repetition's seed; the ask
time is the CPU time of the last 500 trials' asks, the quality the best anytime loss found.
"""

import time
import warnings

import optuna

from explorer.anytime import anytime_loss, parse_budget
from explorer.cost import get_device, model_cost
from explorer.space import SearchSpace
from explorer.study.sampling import RecentTrialsTPE

from harness import Bench, interleave

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


if __name__ == "__main__":
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    bench = Bench(__file__, "The sampler on a long study: ask cost and the best found", __doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=1500, help="trials per study (the ask time is over the last 500)")
    args = bench.parse_args(ap)
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
