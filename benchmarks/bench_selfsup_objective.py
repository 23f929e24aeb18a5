"""Where does the self-supervised objective (issue 13) put its minimum, without any network?

For validation frames of the synthetic sequences, one free depth value per pixel is optimised
(Adam; :func:`explorer.training.depth_hints.compute_hints`, which makes depth hints) on exactly the loss training uses (:mod:`explorer.training.selfsup`: photometric reprojection with the
data's poses, per-pixel minimum, auto-masking, edge-aware smoothness, the scan term), starting from
path 0 (the scan filled column-wise) or from a constant 2.5 m. If the objective's minimum were the
true depth, RMSE would fall; if it rises while the photometric error falls below the true depth's,
the objective itself (not the network or its training) is what self-supervision lacks at this
resolution. Smoothness weights are compared on the same frames, interleaved; each repetition is a
disjoint set of frames. Prints every repetition and the medians.

    .venv/bin/python benchmarks/bench_selfsup_objective.py [--weights 1e-3,1e-2,1e-1] [--iters 400]
"""

import argparse
import statistics
import time

import torch
from torch.utils.data import DataLoader

from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.training.depth_hints import compute_hints
from explorer.model.exits import DEPTH_INIT_M, interpolate_scan
from explorer.training.selfsup import SCAN_WEIGHT, reprojection_loss, warp

SIZE = (64, 64)


def rmse(depth: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean over images of the per-image RMSE on valid pixels (the project's convention)."""
    valid = gt > 0
    return float(torch.stack([((d[v] - g[v]) ** 2).mean().sqrt() for d, g, v in zip(depth, gt, valid)]).mean())


def photometric(depth: torch.Tensor, batch: dict) -> torch.Tensor:
    sources = [batch["sources"][:, k] for k in range(2)]
    warped = [warp(s, depth, batch["K"], batch["pose"][:, k]) for k, s in enumerate(sources)]
    return reprojection_loss(batch["image"], sources, warped)[0].mean()


def optimise(batch: dict, smoothness_weight: float, init: str, iters: int, lr: float) -> dict:
    """The free depth map after ``iters`` steps of the very optimisation that makes depth hints."""
    start = interpolate_scan(batch["scan"], SIZE[0]) if init == "path0" else \
        torch.full_like(batch["depth"], DEPTH_INIT_M)
    d = compute_hints(batch, iters, smoothness_weight, lr, start)
    with torch.no_grad():
        return {"rmse": rmse(d, batch["depth"]), "photometric": float(photometric(d, batch)),
                "start_rmse": rmse(start, batch["depth"])}


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--weights", default="1e-3,1e-2,1e-1", help="smoothness weights to compare, comma-separated")
    ap.add_argument("--inits", default="path0,constant", help="starting depths: path0 and/or constant")
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--lr", type=float, default=0.05, help="Adam step on depth (metres)")
    ap.add_argument("--repeats", type=int, default=3, help="disjoint sets of validation frames")
    ap.add_argument("--frames", type=int, default=16, help="frames per repetition")
    args = ap.parse_args()
    torch.set_num_threads(2)
    torch.manual_seed(0)  # auto-masking's tie-breaking noise

    # the data bench_selfsup trains on (its validation frames), more only when more are asked for
    cfg = SyntheticSequenceConfig(train=480, val=max(48, args.frames * args.repeats), height=128, width=128)
    val = SequenceDataset(SyntheticSequences(ensure_synthetic_sequences(cfg), "val"), SIZE, name="synthetic-seq")
    batches = list(DataLoader(val, batch_size=args.frames))[:args.repeats]
    weights = [float(w) for w in args.weights.split(",")]
    inits = [i.strip() for i in args.inits.split(",")]
    print(f"{len(batches)} repetitions of {args.frames} validation frames at {SIZE[0]}x{SIZE[1]}, "
          f"{args.iters} Adam steps (lr {args.lr}) on free per-pixel depth; scan weight {SCAN_WEIGHT}")
    results: dict[tuple[str, float], list[dict]] = {(i, w): [] for i in inits for w in weights}
    truth = []
    for rep, batch in enumerate(batches):
        gt = batch["depth"]
        truth.append(float(photometric(torch.where(gt > 0, gt, torch.full_like(gt, 5.0)), batch)))
        print(f"rep {rep}: photometric error of the true depth {truth[-1]:.5f}")
        for init in inits:          # interleaved: every setting sees the machine and the frames of this rep
            for w in weights:
                t0 = time.perf_counter()
                r = optimise(batch, w, init, args.iters, args.lr)
                results[(init, w)].append(r)
                print(f"rep {rep} start {init:8s} smoothness {w:g}: RMSE {r['start_rmse']:.3f} -> {r['rmse']:.3f} m, "
                      f"photometric {r['photometric']:.5f}; {time.perf_counter() - t0:.0f} s", flush=True)
    med = statistics.median
    print(f"\nmedians over {len(batches)} repetitions (true depth's photometric error {med(truth):.5f}):")
    for (init, w), rs in results.items():
        print(f"  start {init:8s} smoothness {w:g}: RMSE {med([r['start_rmse'] for r in rs]):.3f} -> "
              f"{med([r['rmse'] for r in rs]):.3f} m (reps {' / '.join(format(r['rmse'], '.3f') for r in rs)}), "
              f"photometric {med([r['photometric'] for r in rs]):.5f}")
