"""Finalists retrained one after another against ``--workers N`` processes at once: the wall time of
retraining the same jobs (K finalists of the default space and the paper design, the finalists'
recipe at a reduced step count) both ways, and the ratio. On a CPU the workers share the cores, so
the gain is what running whole trainings side by side adds over PyTorch's threads inside one; on a
machine with several GPUs every worker has a GPU of its own (run it there with ``--accelerator cuda``).

    python benchmarks/bench_finalists.py [--reps 3] [--finalists 2] [--steps 60] [--workers 2]
    python benchmarks/bench_finalists.py --accelerator cuda --size 224x224 --batch-size 64   # a GPU's study

Each repetition retrains the jobs sequentially and in parallel, in an order that rotates, in fresh
folders (nothing resumes); the estimates they are chosen from are the same every time.
"""

import dataclasses
import random
import tempfile
import time
from pathlib import Path

import optuna

from explorer.data import open_dataset
from explorer.space import SearchSpace
from explorer.study.config import SearchConfig
from explorer.study.finalists import finalist_trials, retrain_finalists

from harness import Bench, image_size, rotated


def _estimates(config: SearchConfig, count: int, seed: int = 0) -> list[optuna.trial.FrozenTrial]:
    """``count`` random candidates of the space with made-up estimates (what retraining starts from)."""
    space, rng = SearchSpace.from_yaml(config.space), random.Random(seed)
    sampler = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed))
    out = []
    for _ in range(count):
        cand = space.sample(sampler.ask())
        out.append(optuna.trial.create_trial(values=[rng.uniform(0.3, 0.6)], user_attrs={
            "candidate": cand.to_dict(), "candidate_key": cand.key, "path_metrics": [], "workloads": {}}))
    return out


def _retrain(config: SearchConfig, estimates, workers: int) -> float:
    study = optuna.create_study(study_name=config.study, storage=optuna.storages.InMemoryStorage())
    for t in estimates:
        study.add_trial(t)
    with tempfile.TemporaryDirectory() as reports:
        start = time.perf_counter()
        retrain_finalists(study, config.resolve(), Path(reports), workers=workers)
        seconds = time.perf_counter() - start
    expected = config.finalists + len(config.baselines)
    if len(finalist_trials(study)) != expected:
        raise SystemExit(f"{len(finalist_trials(study))} retrained, not {expected}")
    return seconds


if __name__ == "__main__":
    bench = Bench(__file__, "Finalists retrained sequentially and by worker processes at once", __doc__)
    ap = bench.parser()
    ap.add_argument("--finalists", type=int, default=2, help="finalists retrained (the paper design beside them)")
    ap.add_argument("--steps", type=int, default=60, help="training steps of each retraining")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the parallel run")
    ap.add_argument("--accelerator", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--size", type=image_size, help="train and deploy at this size, HxW (default: the search's "
                    "defaults, 64x64 then tuned at 224x224); 224x224 with --batch-size 64 is a GPU's study")
    ap.add_argument("--batch-size", type=int, default=16, help="frames a step (default 16)")
    args = bench.parse_args(ap)
    sizes = {"train_size": args.size, "input_size": args.size} if args.size else {}
    config = SearchConfig(study="bench-finalists", finalists=args.finalists, finalist_steps=args.steps,
                          baselines=("paper",), accelerator=args.accelerator, keep_weights=False,
                          batch_size=args.batch_size, **sizes)
    estimates = _estimates(config, 12)
    open_dataset(config.data, "train", config.train_size, seed=config.seed)   # generated once, before timing
    open_dataset(config.data, "val", config.train_size, train_augment=False)
    bench.figure("sequential_s", f"{args.finalists} finalists + paper design, one after another", "s", "lower")
    bench.figure("parallel_s", f"the same, {args.workers} workers at once", "s", "lower")
    bench.figure("speedup", "sequential / parallel", "x", "higher")
    for rep in bench.repetitions():
        took = {}
        for mode in rotated(["sequential", "parallel"], rep):
            took[mode] = _retrain(dataclasses.replace(config, study=f"bench-{mode}"), estimates,
                                  1 if mode == "sequential" else args.workers)
        bench.add("sequential_s", took["sequential"])
        bench.add("parallel_s", took["parallel"])
        bench.add("speedup", took["sequential"] / took["parallel"])
    bench.finish()
