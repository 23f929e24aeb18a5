"""How long a reference network takes to retrain as a study's baseline, as ``--time-limit`` measures
it, beside the estimate it falls back on without a measurement (MACs at the training size over the
paper design's, ``explorer.study.search.baseline_load``): seconds per training step (the finalists'
recipe) of the paper design and of each reference network, measured by the same call the plan makes
(``explorer.study.planning.measure_speeds``). The time plan of a study is only as good as these
ratios. With --study, also the finalists that study would retrain.

    python benchmarks/bench_baseline_training.py [--reps 3] [--steps 12]
        [--references s2d-resnet18,monodepth2-resnet18,fastdepth-pruned] [--study DB --finalists 3]

Each repetition measures the paper design, then every reference network and finalist, in an order
that rotates between repetitions.
"""

from __future__ import annotations

import torch

from explorer.data import open_dataset
from explorer.study.planning import measure_speeds
from explorer.study.search import SearchConfig, baseline_load
from explorer.study import trial_record

from harness import Bench, rotated


def finalists_of(study_file: str, count: int) -> tuple:
    import optuna
    from explorer.space import Candidate
    from explorer.study.finalists import choose_finalists
    study = optuna.load_study(study_name=None, storage=f"sqlite:///{study_file}")
    return tuple(Candidate.from_dict(trial_record(t).candidate) for t in choose_finalists(study, count))


if __name__ == "__main__":
    bench = Bench(__file__, "Reference networks' training step against the paper design's", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--references", default="s2d-resnet18,monodepth2-resnet18,fastdepth-pruned")
    ap.add_argument("--study", help="a study's sqlite file: its finalists are measured too")
    ap.add_argument("--finalists", type=int, default=3)
    args = bench.parse_args(ap)
    names = tuple(n for n in args.references.split(",") if n)
    finalists = finalists_of(args.study, args.finalists) if args.study else ()
    # what `explorer search --time-limit` measures: the same call, with the study's default recipe
    cfg = SearchConfig(study="bench", baselines=names, val_limit=8)
    train_set = open_dataset(cfg.data, "train", cfg.train_size)
    val_set = open_dataset("synthetic:48:16", "val", cfg.train_size, train_augment=False)
    bench.figure("paper_step_s", "paper design, seconds a step", "s", "lower")
    for n in names:
        bench.figure(f"{n}_step_s", f"{n}, seconds a step", "s", "lower")
        bench.figure(f"{n}_ratio", f"{n} / paper design step", "x", None)
    for i, c in enumerate(finalists):
        bench.figure(f"finalist{i}_ratio", f"finalist {c.key} / paper design step", "x", None)
    bench.note("by MACs (the estimate without a measurement): " + ", ".join(
        f"{n} {baseline_load(SearchConfig(study='bench', baselines=(n,))):.2f}x" for n in names))
    for rep in bench.repetitions():
        order = tuple(rotated(list(names), rep))
        speeds = measure_speeds(cfg, train_set, val_set, torch.device("cpu"), supernet=False, steps=args.steps,
                                baselines=order, finalists=finalists)
        bench.add("paper_step_s", speeds.retrain_step_s)
        for n in names:
            bench.add(f"{n}_step_s", dict(speeds.baseline_step_s)[n])
            bench.add(f"{n}_ratio", speeds.relative_training(n))
        for i, step in enumerate(speeds.finalist_step_s):
            bench.add(f"finalist{i}_ratio", step / speeds.retrain_step_s)
    bench.finish()
