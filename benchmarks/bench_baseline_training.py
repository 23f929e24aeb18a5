"""How long a reference network takes to retrain as a study's baseline, as `--time-limit` measures it,
beside the estimate it falls back on without a measurement (MACs at the training size over the paper
design's, `search.baseline_load`): seconds per training step (batch 16 at 64x64, the finalists' recipe) of the paper design and of
each reference network, measured by the same call the plan makes (explorer.study.planning.measure_speeds),
--reps times; every repetition and the medians are printed. With --study, also the finalists that
study would retrain (what the plan measures when sampling ends).

    .venv/bin/python benchmarks/bench_baseline_training.py [--reps 3] [--steps 12]
        [--references s2d-resnet18,monodepth2-resnet18,fastdepth-pruned] [--study DB --finalists 3]
"""

from __future__ import annotations

import argparse
import statistics

import torch

from explorer.data import open_dataset
from explorer.study.planning import measure_speeds
from explorer.study.search import SearchConfig, baseline_load

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--references", default="s2d-resnet18,monodepth2-resnet18,fastdepth-pruned")
    ap.add_argument("--study", help="a study's sqlite file: its finalists are measured too")
    ap.add_argument("--finalists", type=int, default=3)
    args = ap.parse_args()
    names = tuple(n for n in args.references.split(",") if n)
    finalists = ()
    if args.study:
        import optuna
        from explorer.study.finalists import choose_finalists
        from explorer.space import Candidate
        study = optuna.load_study(study_name=None, storage=f"sqlite:///{args.study}")
        finalists = tuple(Candidate.from_dict(t.user_attrs["candidate"])
                          for t in choose_finalists(study, args.finalists))
    finalist_ratios: list[list[float]] = [[] for _ in finalists]
    # what `explorer search --time-limit` measures: the same call, with the study's default recipe
    cfg = SearchConfig(study="bench", baselines=names, val_limit=8)
    train_set = open_dataset(cfg.data, "train", cfg.train_size)
    val_set = open_dataset("synthetic:48:16", "val", cfg.train_size, train_augment=False)
    ratios: dict[str, list[float]] = {n: [] for n in names}
    for rep in range(args.reps):   # each rep measures the paper design, then every reference
        speeds = measure_speeds(cfg, train_set, val_set, torch.device("cpu"), supernet=False, steps=args.steps,
                                baselines=names, finalists=finalists)
        for n in names:
            ratios[n].append(speeds.relative_training(n))
        for i, step in enumerate(speeds.finalist_step_s):
            finalist_ratios[i].append(step / speeds.retrain_step_s)
        print(f"rep {rep + 1}: paper design {speeds.retrain_step_s:.3f} s a step; "
              + ", ".join(f"{n} {dict(speeds.baseline_step_s)[n]:.3f} s ({ratios[n][-1]:.2f}x)" for n in names)
              + "".join(f", finalist {c.key} {r[-1]:.2f}x" for c, r in zip(finalists, finalist_ratios)),
              flush=True)
    for n in names:
        by_macs = baseline_load(SearchConfig(study="bench", baselines=(n,)))
        print(f"{n}: median {statistics.median(ratios[n]):.2f}x the paper design's step (reps "
              f"{' / '.join(f'{r:.2f}' for r in ratios[n])}); by MACs {by_macs:.2f}x")
    for c, r in zip(finalists, finalist_ratios):
        print(f"finalist {c.key}: median {statistics.median(r):.2f}x the paper design's step (reps "
              f"{' / '.join(f'{x:.2f}' for x in r)})")
