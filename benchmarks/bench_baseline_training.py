"""How long a reference network takes to retrain as a study's baseline, against what `--time-limit`
plans for it (its MACs at the training size over the paper design's, `search.baseline_load`):
seconds per training step (batch 16 at 64x64, the finalists' recipe) of the paper design and of
each reference network, interleaved, --reps times; every repetition and the medians are printed.

    .venv/bin/python benchmarks/bench_baseline_training.py [--reps 3] [--steps 12]
        [--references s2d-resnet18,monodepth2-resnet18,fastdepth-pruned]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from explorer.data import open_dataset
from explorer.model import build_network
from explorer.model.reference import ReferenceDepthNet
from explorer.search import SearchConfig, baseline_load
from explorer.space import paper_candidate
from explorer.train import TrainConfig, train


def step_seconds(net, train_set, val_set, steps: int) -> float:
    """Median step time after the first two (allocation and first kernels run slow)."""
    marks: dict[int, float] = {}
    cfg = TrainConfig(steps=steps, batch_size=16, input_size=(64, 64))
    train(net, train_set, val_set, cfg, progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()),
          val_limit=8)
    return statistics.median(marks[s] - marks[s - 1] for s in range(3, steps + 1))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--references", default="s2d-resnet18,monodepth2-resnet18,fastdepth-pruned")
    args = ap.parse_args()
    names = ["paper"] + [n for n in args.references.split(",") if n]
    train_set = open_dataset("synthetic", "train", (64, 64))
    val_set = open_dataset("synthetic:48:16", "val", (64, 64), train_augment=False)
    seconds: dict[str, list[float]] = {n: [] for n in names}
    for rep in range(args.reps):
        for name in names:   # interleaved
            torch.manual_seed(rep)
            net = build_network(paper_candidate()) if name == "paper" else ReferenceDepthNet(name)
            seconds[name].append(step_seconds(net, train_set, val_set, args.steps))
        print(f"rep {rep + 1}: " + ", ".join(f"{n} {seconds[n][-1]:.3f} s" for n in names), flush=True)
    paper = statistics.median(seconds["paper"])
    for name in names[1:]:
        planned = baseline_load(SearchConfig(study="bench", baselines=(name,)))
        measured = statistics.median(seconds[name]) / paper
        print(f"{name}: {statistics.median(seconds[name]):.3f} s a step, {measured:.2f}x the paper design's "
              f"{paper:.3f} s; the plan counts {planned:.2f}x")
