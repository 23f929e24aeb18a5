"""Self-supervised training from video with metric scale from the 2D LiDAR, on synthetic sequences:
the paper design trained supervised (L1 on exact depth), self-supervised with the scan term
(photometric reprojection, pose network trained jointly), self-supervised with the scan term and depth
hints (the data's poses), and self-supervised without the scan term (depth only up to scale), for the
same steps. Self-supervision is meant to approach supervised accuracy without depth labels (target:
last-path RMSE within 1.3x of supervised), and the scan term is what gives it metric scale.

    python benchmarks/bench_selfsup.py [--reps 3] [--steps 150] [--batch 8]
        [--kinds supervised,self+scan,hints,noscan] [--poses net|given]

Each repetition is one seed; within it every kind is trained, in an order that rotates. Figures: each
kind's last-path RMSE and whether every exit beats path 0 (1 or 0), the ratios to supervised, and for
the run without the scan term its scale (median over images of median(gt) / median(prediction)) and
its median-scaled RMSE.
"""

import dataclasses
import statistics
import time

import torch
from torch.utils.data import DataLoader

from explorer.data.sequences import (SequenceDataset, SyntheticSequenceConfig, SyntheticSequences,
                                     ensure_synthetic_sequences)
from explorer.model import build_network
from explorer.space import paper_candidate
from explorer.training.depth_hints import with_hints
from explorer.training.train import PROXY, evaluate, train

from harness import Bench, interleave

SIZE = (64, 64)
KINDS = {"supervised": "supervised", "self+scan": "self_scan", "hints": "self_hints", "noscan": "self_noscan"}


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
    supervision, scan_loss = {"supervised": ("supervised", True), "self_scan": ("self", True),
                              "self_hints": ("self", True), "self_noscan": ("self", False)}[kind]
    hints = kind == "self_hints"
    cfg = dataclasses.replace(PROXY, steps=steps, batch_size=batch, input_size=SIZE, seed=seed,
                              supervision=supervision, scan_loss=scan_loss, hints=hints,
                              poses="given" if hints else poses)
    torch.manual_seed(seed)
    net = build_network(paper_candidate())
    t0 = time.perf_counter()
    result = train(net, train_set, val_set, cfg)
    rmse = list(result.metrics["rmse"])
    out = {"seconds": time.perf_counter() - t0, "rmse": rmse, "beats_path0": all(r < rmse[0] for r in rmse[1:])}
    if not scan_loss:
        out["median_scaled_rmse"] = rmse  # train() evaluates a scale-free model with median scaling
        out["rmse"] = list(evaluate(net, val_set, median_scaling=False)["rmse"])
        out["scale_ratio"] = scale_ratio(net, val_set)
    return out


def declare(bench: Bench, kinds: list[str]) -> None:
    for k in kinds:
        bench.figure(f"{k}_last_rmse", f"{k}: last-path RMSE", "m", "lower")
        bench.figure(f"{k}_beats_path0", f"{k}: every exit beats path 0 (1 = yes)", "", "higher")
        bench.figure(f"{k}_s", f"{k}: training time", "s", "lower")
    for k in ("self_scan", "self_hints"):
        if k in kinds and "supervised" in kinds:
            bench.figure(f"{k}_over_supervised", f"{k} / supervised last-path RMSE (target <= 1.3)", "x", "lower")
    if "self_noscan" in kinds:
        bench.figure("noscan_scale", "without the scan term: scale gt / prediction (1 = metric)", "", None)
        bench.figure("noscan_median_scaled_rmse", "without the scan term: median-scaled last-path RMSE", "m", "lower")


if __name__ == "__main__":
    bench = Bench(__file__, "Self-supervised training with the scan term against supervised", __doc__)
    ap = bench.parser()
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
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    import explorer.training.selfsup as selfsup
    if args.scan_weight is not None:
        selfsup.SCAN_WEIGHT = args.scan_weight
    if args.smoothness_weight is not None:
        selfsup.SMOOTHNESS_WEIGHT = args.smoothness_weight
    # rendered at 128x128 (a third of the default's pixels) since training runs at 64x64; cached
    path = ensure_synthetic_sequences(SyntheticSequenceConfig(train=args.train, val=args.val, height=128, width=128))
    train_set = SequenceDataset(SyntheticSequences(path, "train"), SIZE, name="synthetic-seq")
    val_set = SequenceDataset(SyntheticSequences(path, "val"), SIZE, name="synthetic-seq")
    kinds = [KINDS[k.strip()] for k in args.kinds.split(",") if k.strip()]
    sets = {k: train_set for k in kinds}
    if "self_hints" in kinds:
        sets["self_hints"] = with_hints(train_set)   # cached after the first run
    declare(bench, kinds)
    bench.note(f"paper design, {args.steps} steps, batch {args.batch}, {SIZE[0]}x{SIZE[1]}; scan weight "
               f"{selfsup.SCAN_WEIGHT}, smoothness weight {selfsup.SMOOTHNESS_WEIGHT}; each repetition is one seed")
    for rep in bench.repetitions():
        got = interleave({k: (lambda k=k: run(k, rep, args.steps, args.batch, sets[k], val_set, args.poses))
                          for k in kinds}, rep)
        for k, r in got.items():
            bench.add(f"{k}_last_rmse", r["rmse"][-1])
            bench.add(f"{k}_beats_path0", float(r["beats_path0"]))
            bench.add(f"{k}_s", r["seconds"])
        for k in ("self_scan", "self_hints"):
            if k in got and "supervised" in got:
                bench.add(f"{k}_over_supervised", got[k]["rmse"][-1] / got["supervised"]["rmse"][-1])
        if "self_noscan" in got:
            bench.add("noscan_scale", got["self_noscan"]["scale_ratio"])
            bench.add("noscan_median_scaled_rmse", got["self_noscan"]["median_scaled_rmse"][-1])
    bench.finish()
