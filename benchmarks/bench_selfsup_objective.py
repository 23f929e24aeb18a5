"""Where does the self-supervised objective put its minimum, without any network? For validation
frames of the synthetic sequences, one free depth value per pixel is optimised (Adam;
:func:`explorer.training.depth_hints.compute_hints`, which makes depth hints) on exactly the loss
training uses (:mod:`explorer.training.selfsup`: photometric reprojection with the data's poses,
per-pixel minimum, auto-masking, edge-aware smoothness, the scan term), starting from path 0 (the scan
filled column-wise) or from a constant depth. If the objective's minimum were the true depth, RMSE
would fall; if it rises while the photometric error falls below the true depth's, the objective itself
(not the network or its training) is what self-supervision lacks at this resolution.

    python benchmarks/bench_selfsup_objective.py [--reps 3] [--weights 1e-3,1e-2,1e-1] [--iters 400]

Each repetition is a disjoint set of validation frames; within it every start and smoothness weight
is optimised on the same frames, in an order that rotates.
"""

import torch
from torch.utils.data import DataLoader

from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.model.exits import DEPTH_INIT_M, interpolate_scan
from explorer.training.depth_hints import compute_hints
from explorer.training.selfsup import SCAN_WEIGHT, reprojection_loss, warp

from harness import Bench, interleave

SIZE = (64, 64)


def rmse(depth: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean over images of the per-image RMSE on valid pixels (the project's convention)."""
    valid = gt > 0
    return float(torch.stack([((d[v] - g[v]) ** 2).mean().sqrt() for d, g, v in zip(depth, gt, valid)]).mean())


def photometric(depth: torch.Tensor, batch: dict) -> torch.Tensor:
    sources = [batch["sources"][:, k] for k in range(2)]
    warped = [warp(s, depth, batch["K"], batch["pose"][:, k]) for k, s in enumerate(sources)]
    return reprojection_loss(batch["image"], sources, warped)[0].mean()


def start_depth(batch: dict, init: str) -> torch.Tensor:
    return interpolate_scan(batch["scan"], SIZE[0]) if init == "path0" else torch.full_like(batch["depth"],
                                                                                             DEPTH_INIT_M)


def optimise(batch: dict, smoothness_weight: float, init: str, iters: int, lr: float) -> dict:
    """The free depth map after ``iters`` steps of the very optimisation that makes depth hints."""
    d = compute_hints(batch, iters, smoothness_weight, lr, start_depth(batch, init))
    with torch.no_grad():
        return {"rmse": rmse(d, batch["depth"]), "photometric": float(photometric(d, batch))}


if __name__ == "__main__":
    bench = Bench(__file__, "Self-supervised objective's minimum on free per-pixel depth", __doc__)
    ap = bench.parser()
    ap.add_argument("--weights", default="1e-3,1e-2,1e-1", help="smoothness weights to compare, comma-separated")
    ap.add_argument("--inits", default="path0,constant", help="starting depths: path0 and/or constant")
    ap.add_argument("--iters", type=int, default=400)
    ap.add_argument("--lr", type=float, default=0.05, help="Adam step on depth (metres)")
    ap.add_argument("--frames", type=int, default=16, help="frames per repetition")
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    torch.manual_seed(0)  # auto-masking's tie-breaking noise
    # the data bench_selfsup trains on (its validation frames), more only when more are asked for
    cfg = SyntheticSequenceConfig(train=480, val=max(48, args.frames * args.reps), height=128, width=128)
    val = SequenceDataset(SyntheticSequences(ensure_synthetic_sequences(cfg), "val"), SIZE, name="synthetic-seq")
    batches = list(DataLoader(val, batch_size=args.frames))[:args.reps]
    inits = [i.strip() for i in args.inits.split(",") if i.strip()]
    settings = {(i, float(w)): f"{i}_w{w}" for i in inits for w in args.weights.split(",")}
    bench.figure("truth_photometric", "photometric error of the true depth", "", None)
    for init in inits:
        bench.figure(f"{init}_start_rmse", f"start {init}: RMSE before optimising", "m", None)
    for (init, w), key in settings.items():
        bench.figure(f"{key}_rmse", f"start {init}, smoothness {w:g}: RMSE after", "m", "lower")
        bench.figure(f"{key}_photometric", f"start {init}, smoothness {w:g}: photometric error after", "", None)
    bench.note(f"{args.frames} validation frames a repetition at {SIZE[0]}x{SIZE[1]}, {args.iters} Adam steps "
               f"(lr {args.lr}) on free per-pixel depth; scan weight {SCAN_WEIGHT}")
    for rep in bench.repetitions(min(args.reps, len(batches))):
        batch = batches[rep]
        gt = batch["depth"]
        bench.add("truth_photometric", float(photometric(torch.where(gt > 0, gt, torch.full_like(gt, 5.0)), batch)))
        for init in inits:
            bench.add(f"{init}_start_rmse", rmse(start_depth(batch, init), gt))
        got = interleave({key: (lambda s=s: optimise(batch, s[1], s[0], args.iters, args.lr))
                          for s, key in settings.items()}, rep)
        for key, r in got.items():
            bench.add(f"{key}_rmse", r["rmse"])
            bench.add(f"{key}_photometric", r["photometric"])
    bench.finish()
