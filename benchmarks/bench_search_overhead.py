"""A search's bookkeeping per trial, without the evaluator: the sampler (TPE as a search sets it up),
sampling a candidate of the default space, costing its paths on the TX2 profile, and the storage
writes of its parameters and attributes, and the reads the sampler makes. Five storages: the journal
file a search on this machine keeps its study in (:func:`explorer.study.storage.open_storage`, synced
to the disk at trial state changes), the same journal as Optuna's file backend writes it (synced
after every line),
SQLite as Optuna opens it (a rollback journal, synced at every commit), SQLite as ``explorer search``
opens it for ``--storage sqlite:///...`` (a write-ahead log, synced at checkpoints), and memory (what
the sampler and the costing take alone).

    python benchmarks/bench_search_overhead.py [--reps 3] [--trials 150]

Each repetition runs ``--trials`` trials on a fresh study with each storage, in an order that rotates,
and records wall and CPU milliseconds a trial. Evaluating a candidate with the supernet takes about
0.1 s on a GPU and 0.3-1 s on two CPU cores; what is here is what comes on top.
"""

import shutil
import tempfile
import time
from pathlib import Path

import optuna

from explorer.cost import get_device, model_cost
from explorer.space import SearchSpace
from explorer.study.config import SearchConfig
from explorer.study.search import make_sampler
from explorer.study.storage import open_storage

from harness import Bench, rotated

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


if __name__ == "__main__":
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    bench = Bench(__file__, "A search's bookkeeping per trial: sampler, costing and storage", __doc__)
    ap = bench.parser()
    ap.add_argument("--trials", type=int, default=150, help="trials per storage and repetition")
    args = bench.parse_args(ap)
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
