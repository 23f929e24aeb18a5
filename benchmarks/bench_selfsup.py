"""Self-supervised training from video with metric scale from the 2D LiDAR (issue 13), on synthetic
sequences: the paper design trained

  - supervised (L1 on exact depth),
  - self-supervised with the scan term (photometric reprojection, pose network trained jointly),
  - self-supervised with the scan term and depth hints (``--kinds ...,hints``; the data's poses),
  - self-supervised without the scan term (depth only up to scale),

for the same steps, each seed interleaving the three. Prints every repetition and the medians of:
the last path's RMSE of self+scan over supervised (target <= 1.3), how far off the scale is without
the scan term and without median scaling (median over images of median(gt) / median(prediction)),
that run's RMSE with and without median scaling, and whether every exit beats path 0.

    .venv/bin/python benchmarks/bench_selfsup.py [--seeds 3] [--steps 150] [--batch 8]
"""

import argparse
import dataclasses
import statistics
import time

import torch
from torch.utils.data import DataLoader

from explorer.training.depth_hints import with_hints
from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.model import build_network
from explorer.space import paper_candidate
from explorer.training.train import PROXY, evaluate, train

SIZE = (64, 64)


def scale_ratio(net, dataset) -> float:
    """Median over images of median(gt) / median(last path): 1.0 = metric."""
    ratios = []
    net.eval()
    with torch.no_grad():
        for batch in DataLoader(dataset, batch_size=16):
            out = net(batch["image"], batch["scan"], int(batch["scan_row"][0]))[-1]
            for pred, gt in zip(out, batch["depth"]):
                valid = gt > 0
                ratios.append(float(gt[valid].median() / pred[valid].median().clamp(min=1e-6)))
    return statistics.median(ratios)


def run(kind: str, seed: int, steps: int, batch: int, train_set, val_set, poses: str = "net") -> dict:
    supervision, scan_loss = {"supervised": ("supervised", True), "self+scan": ("self", True),
                              "self+hints": ("self", True), "self, no scan": ("self", False)}[kind]
    hints = kind == "self+hints"
    cfg = dataclasses.replace(PROXY, steps=steps, batch_size=batch, input_size=SIZE, seed=seed,
                              supervision=supervision, scan_loss=scan_loss, hints=hints,
                              poses="given" if hints else poses)
    torch.manual_seed(seed)
    net = build_network(paper_candidate())
    t0 = time.perf_counter()
    result = train(net, train_set, val_set, cfg)
    rmse = list(result.metrics["rmse"])
    out = {"kind": kind, "seed": seed, "seconds": time.perf_counter() - t0, "rmse": rmse,
           "every_exit_beats_path0": all(r < rmse[0] for r in rmse[1:])}
    if not scan_loss:
        out["median_scaled_rmse"] = rmse  # train() evaluates a scale-free model with median scaling
        out["rmse"] = list(evaluate(net, val_set, median_scaling=False)["rmse"])
        out["scale_ratio"] = scale_ratio(net, val_set)
        out["every_exit_beats_path0"] = all(r < rmse[0] for r in rmse[1:])
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--train", type=int, default=480, help="target frames (3 per rendered room)")
    ap.add_argument("--val", type=int, default=48)
    ap.add_argument("--scan-weight", type=float, default=None,
                    help="weight of the scan term (default: explorer.training.selfsup.SCAN_WEIGHT)")
    ap.add_argument("--smoothness-weight", type=float, default=None,
                    help="weight of the edge-aware smoothness (default: explorer.training.selfsup.SMOOTHNESS_WEIGHT)")
    ap.add_argument("--poses", default="net", choices=["net", "given"],
                    help="self-supervision's camera motion: the pose network (default) or the data's poses")
    ap.add_argument("--kinds", default="supervised,self+scan,hints,noscan",
                    help="which trainings, comma-separated: supervised, self+scan, hints (self+scan with depth "
                    "hints and the data's poses), noscan (default: all four)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    import explorer.training.selfsup
    if args.scan_weight is not None:
        explorer.training.selfsup.SCAN_WEIGHT = args.scan_weight
    if args.smoothness_weight is not None:
        explorer.training.selfsup.SMOOTHNESS_WEIGHT = args.smoothness_weight
    print(f"scan term weight {explorer.training.selfsup.SCAN_WEIGHT}, smoothness weight {explorer.training.selfsup.SMOOTHNESS_WEIGHT}")

    # rendered at 128x128 (a third of the default's pixels) since training runs at 64x64
    cfg = SyntheticSequenceConfig(train=args.train, val=args.val, height=128, width=128)
    t0 = time.perf_counter()
    path = ensure_synthetic_sequences(cfg)
    print(f"synthetic sequences {args.train}:{args.val} at 128x128: ready in {time.perf_counter() - t0:.0f} s "
          "(cached after the first run)")
    train_set = SequenceDataset(SyntheticSequences(path, "train"), SIZE, name="synthetic-seq")
    val_set = SequenceDataset(SyntheticSequences(path, "val"), SIZE, name="synthetic-seq")

    names = {"supervised": "supervised", "self+scan": "self+scan", "hints": "self+hints", "noscan": "self, no scan"}
    kinds = tuple(names[k.strip()] for k in args.kinds.split(",") if k.strip())
    hinted = None
    if "self+hints" in kinds:
        t0 = time.perf_counter()
        hinted = with_hints(train_set)
        print(f"depth hints for {len(train_set)} frames: ready in {time.perf_counter() - t0:.0f} s (cached after the first run)")
    results = {k: [] for k in kinds}
    for seed in range(args.seeds):
        for kind in kinds:  # interleaved: machine load drifts over the run
            r = run(kind, seed, args.steps, args.batch, hinted if kind == "self+hints" else train_set, val_set,
                    args.poses)
            results[kind].append(r)
            extra = (f", scale gt/pred {r['scale_ratio']:.3f}, median-scaled RMSE "
                     f"{r['median_scaled_rmse'][-1]:.3f}") if "scale_ratio" in r else ""
            print(f"seed {seed} {kind:14s} per-path RMSE {' / '.join(f'{x:.3f}' for x in r['rmse'])} "
                  f"(every exit < path 0: {r['every_exit_beats_path0']}){extra}; {r['seconds']:.0f} s", flush=True)

    med = lambda xs: statistics.median(xs)  # noqa: E731
    print(f"\nmedians over {args.seeds} seeds, paper design, {args.steps} steps, batch {args.batch}, {SIZE[0]}x{SIZE[1]}:")
    if "supervised" in results and "self+scan" in results:
        sup = [r["rmse"][-1] for r in results["supervised"]]
        selfscan = [r["rmse"][-1] for r in results["self+scan"]]
        ratios = [s / p for s, p in zip(selfscan, sup)]
        print(f"  last-path RMSE: supervised {med(sup):.3f} m, self-supervised + scan {med(selfscan):.3f} m; "
              f"ratio {med(ratios):.2f}x (per seed {', '.join(f'{x:.2f}' for x in ratios)}; target <= 1.3)")
    if "supervised" in results and "self+hints" in results:
        sup = [r["rmse"][-1] for r in results["supervised"]]
        hinted_last = [r["rmse"][-1] for r in results["self+hints"]]
        ratios = [s / p for s, p in zip(hinted_last, sup)]
        print(f"  last-path RMSE: supervised {med(sup):.3f} m, self-supervised + scan + depth hints (data's poses) "
              f"{med(hinted_last):.3f} m; ratio {med(ratios):.2f}x (per seed {', '.join(f'{x:.2f}' for x in ratios)}; "
              "target <= 1.3)")
    if "self, no scan" in results:
        noscan = results["self, no scan"]
        scales = [r["scale_ratio"] for r in noscan]
        print(f"  without the scan term: scale gt/pred {med(scales):.3f} "
              f"(per seed {', '.join(f'{x:.3f}' for x in scales)}), last-path RMSE "
              f"{med([r['rmse'][-1] for r in noscan]):.3f} m unscaled, "
              f"{med([r['median_scaled_rmse'][-1] for r in noscan]):.3f} m median-scaled")
    for kind in kinds:
        per_path = [med([r["rmse"][p] for r in results[kind]]) for p in range(len(results[kind][0]["rmse"]))]
        beats = all(r["every_exit_beats_path0"] for r in results[kind])
        print(f"  {kind:14s} median per-path RMSE {' / '.join(f'{x:.3f}' for x in per_path)}; "
              f"every exit beats path 0 in every seed: {beats}")
    print("  (CPU, 2 cores shared with other work: times are indicative only)")
