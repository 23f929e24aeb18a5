"""Data and training: synthetic generation rate, training throughput at proxy and full resolution,
how proxy rankings agree with longer training (Kendall tau), the paper design's per-path RMSE on
synthetic data after the proxy recipe and after a longer one, and path 0 on the real NYU frames.

    .venv/bin/python benchmarks/bench_data_train.py [--candidates 6] [--long-steps 600]
"""

import argparse
import dataclasses
import random
import tempfile
import time
from pathlib import Path

import torch
from scipy.stats import kendalltau

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.data.synthetic import SyntheticConfig, generate
from explorer.metrics import MetricAverager, depth_metrics
from explorer.model import build_network, interpolate_scan
from explorer.study.search import SearchConfig
from explorer.space import SearchSpace, paper_candidate
from explorer.training.train import TrainConfig, train


def throughput(size, steps=8, batch=16):
    ds = open_dataset("synthetic", "train", size)
    cfg = TrainConfig(steps=steps, batch_size=batch, input_size=size)
    net = build_network(paper_candidate())
    res = train(net, ds, open_dataset("synthetic:48:16", "val", size), cfg, val_limit=16)
    return res.images_per_second


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--candidates", type=int, default=6)
    ap.add_argument("--long-steps", type=int, default=600)
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    args = ap.parse_args()
    torch.set_num_threads(2)

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate(SyntheticConfig(train=192, val=8), Path(tmp) / "s.h5")
        dt = time.perf_counter() - t0
        print(f"synthetic generation: {200 / dt:.1f} frames/s at 224x224 (2,200 default frames: {2200 / (200 / dt) / 60:.1f} min)")

    print(f"training throughput (paper design, batch 16, CPU): proxy 64x64 {throughput((64, 64)):.0f} images/s, "
          f"full 224x224 {throughput((224, 224), steps=4):.1f} images/s")

    search = SearchConfig(study="x")
    proxy = search.train_config()
    proxy = dataclasses.replace(proxy, eval_every=0)
    long = dataclasses.replace(proxy, steps=args.long_steps, input_size=(96, 96))
    tx2 = get_device("tx2")
    train_p, val_p = open_dataset("synthetic", "train", proxy.input_size), open_dataset("synthetic", "val", proxy.input_size)
    train_l, val_l = open_dataset("synthetic", "train", long.input_size), open_dataset("synthetic", "val", long.input_size)
    cands = [paper_candidate()] + random.Random(3).sample(list(SearchSpace.from_yaml("anytime_depth").enumerate()),
                                                          args.candidates - 1)
    short_scores, long_scores = [], []
    for c in cands:
        cost = candidate_cost(c).path_costs(tx2, "time")
        r1 = train(build_network(c), train_p, val_p, proxy, val_limit=None)
        r2 = train(build_network(c), train_l, val_l, long, val_limit=None)
        s1 = anytime_loss(cost, list(r1.metrics["rmse"]), "time:uniform:33ms")
        s2 = anytime_loss(cost, list(r2.metrics["rmse"]), "time:uniform:33ms")
        short_scores.append(s1)
        long_scores.append(s2)
        print(f"  {c.key}: proxy ({proxy.steps} steps @{proxy.input_size[0]}) L={s1:.4f} in {r1.seconds:.0f} s | "
              f"longer ({long.steps} steps @{long.input_size[0]}) L={s2:.4f} in {r2.seconds:.0f} s")
        if c == paper_candidate():
            print("  paper design per-path RMSE, proxy:  " + " ".join(f"{x:.3f}" for x in r1.metrics["rmse"]))
            print("  paper design per-path RMSE, longer: " + " ".join(f"{x:.3f}" for x in r2.metrics["rmse"]))
    tau = kendalltau(short_scores, long_scores)
    print(f"proxy vs longer training: Kendall tau {tau.statistic:.2f} over {len(cands)} candidates (p={tau.pvalue:.2f})")

    nyu = Path(args.data) / "nyu-mini" / "nyu2_mini_test.csv"
    if nyu.is_file():
        ds = open_dataset(f"nyu:{nyu}", "val", (224, 224))
        avg = MetricAverager()
        for i in range(len(ds)):
            it = ds[i]
            avg.add(depth_metrics(interpolate_scan(it["scan"][None], 224)[0], it["depth"]))
        r = avg.result()
        print(f"path 0 on the {len(ds)} nyu-mini frames: RMSE {r['rmse']:.3f} m, REL {r['rel']:.3f}, "
              f"delta1 {r['delta1']:.3f} (paper, full NYU val: 0.987 / 27.9% / 0.661)")
