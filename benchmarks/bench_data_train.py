"""Data and training: synthetic generation rate, training throughput at proxy and full resolution,
how proxy rankings agree with longer training (Kendall tau), the paper design's last-path RMSE on
synthetic data after the proxy recipe and after a longer one, and path 0 on the real NYU frames.
These are the rates that size a study's time plan, and the agreement that justifies ranking
candidates by the proxy recipe.

    python benchmarks/bench_data_train.py [--reps 3] [--candidates 6] [--long-steps 600] [--data DIR]

Generation and the two throughputs alternate within each repetition; the ranking comparison trains
every candidate once with each recipe (one value per figure), and path 0 on nyu-mini is measured
when --data holds it.
"""

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
from explorer.space import SearchSpace, paper_candidate
from explorer.study.search import SearchConfig
from explorer.training.train import TrainConfig, train

from harness import Bench, interleave


def throughput(size, steps=8, batch=16) -> float:
    ds = open_dataset("synthetic", "train", size)
    cfg = TrainConfig(steps=steps, batch_size=batch, input_size=size)
    net = build_network(paper_candidate())
    res = train(net, ds, open_dataset("synthetic:48:16", "val", size), cfg, val_limit=16)
    return res.images_per_second


def generation_rate() -> float:
    """Synthetic frames per second at 224x224 (200 frames)."""
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        generate(SyntheticConfig(train=192, val=8), Path(tmp) / "s.h5")
        return 200 / (time.perf_counter() - t0)


def ranking(bench: Bench, n: int, long_steps: int) -> None:
    """Kendall tau between the proxy recipe's anytime losses and a longer recipe's, over ``n`` candidates."""
    proxy = dataclasses.replace(SearchConfig(study="x").train_config(), eval_every=0)
    recipes = {"proxy": proxy, "long": dataclasses.replace(proxy, steps=long_steps, input_size=(96, 96))}
    tx2 = get_device("tx2")
    sets = {k: (open_dataset("synthetic", "train", r.input_size), open_dataset("synthetic", "val", r.input_size))
            for k, r in recipes.items()}
    cands = [paper_candidate()] + random.Random(3).sample(list(SearchSpace.from_yaml("anytime_depth").enumerate()),
                                                          n - 1)
    scores: dict[str, list[float]] = {k: [] for k in recipes}
    for c in cands:
        cost = candidate_cost(c).path_costs(tx2, "time")
        for k, r in recipes.items():
            res = train(build_network(c), *sets[k], r, val_limit=None)
            scores[k].append(anytime_loss(cost, list(res.metrics["rmse"]), "time:uniform:33ms"))
            if c == paper_candidate():
                bench.add(f"paper_rmse_{k}", res.metrics["rmse"][-1])
            print(f"  {c.key}: {r.steps} steps at {r.input_size[0]}: anytime loss {scores[k][-1]:.4f} "
                  f"in {res.seconds:.0f} s", flush=True)
    long = recipes["long"]
    tau = kendalltau(scores["proxy"], scores["long"])
    bench.add("kendall_tau", tau.statistic)
    bench.note(f"ranking: proxy ({proxy.steps} steps at {proxy.input_size[0]}) against {long.steps} steps at "
               f"{long.input_size[0]}, {n} candidates, p={tau.pvalue:.2f}")


def nyu_path0(bench: Bench, data: Path) -> None:
    nyu = data / "nyu-mini" / "nyu2_mini_test.csv"
    if not nyu.is_file():
        bench.note(f"no {nyu}: path 0 on NYU not measured")
        return
    ds = open_dataset(f"nyu:{nyu}", "val", (224, 224))
    avg = MetricAverager()
    for i in range(len(ds)):
        it = ds[i]
        avg.add(depth_metrics(interpolate_scan(it["scan"][None], 224)[0], it["depth"]))
    r = avg.result()
    bench.add("nyu_path0_rmse", r["rmse"])
    bench.add("nyu_path0_delta1", r["delta1"])
    bench.note(f"path 0 on {len(ds)} nyu-mini frames: REL {r['rel']:.3f} (the paper, full NYU val: RMSE 0.987, "
               "REL 27.9%, delta1 0.661)")


if __name__ == "__main__":
    bench = Bench(__file__, "Data generation, training throughput and proxy ranking fidelity", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=6)
    ap.add_argument("--long-steps", type=int, default=600)
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    bench.figure("generation_fps", "synthetic generation at 224x224", "frames/s", "higher")
    bench.figure("train_proxy_ips", "training throughput, 64x64, batch 16", "images/s", "higher")
    bench.figure("train_full_ips", "training throughput, 224x224, batch 16", "images/s", "higher")
    bench.figure("kendall_tau", "Kendall tau, proxy against longer training", "", "higher")
    bench.figure("paper_rmse_proxy", "paper design last-path RMSE, proxy recipe", "m", "lower")
    bench.figure("paper_rmse_long", "paper design last-path RMSE, longer recipe", "m", "lower")
    bench.figure("nyu_path0_rmse", "path 0 RMSE on nyu-mini", "m", "lower")
    bench.figure("nyu_path0_delta1", "path 0 delta1 on nyu-mini", "", "higher")
    for rep in bench.repetitions():
        got = interleave({"generation_fps": generation_rate, "train_proxy_ips": lambda: throughput((64, 64)),
                          "train_full_ips": lambda: throughput((224, 224), steps=4)}, rep)
        for k, v in got.items():
            bench.add(k, v)
    ranking(bench, args.candidates, args.long_steps)
    nyu_path0(bench, Path(args.data))
    bench.finish()
