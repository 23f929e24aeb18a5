"""Rank fidelity of supernets trained with each sandwich variant (``teacher_depths``: the label-trained
subnet always the deepest, ``max``, or turning over the encoder depths, ``cycle``) against stand-alone
labels: random default-space candidates and the paper design with and without early exits, each
trained alone 600 steps (4x the proxy; cached by benchmarks/_labels.py), tx2, U(0, 33 ms). A search
is only as good as the supernet's ranking; this picks the sandwich that ranks best. Also each
supernet's order of the best candidate of every image encoder, where a sandwich's bias shows.

    python benchmarks/bench_teacher_depths.py [--reps 3] [--steps 400] [--candidates 16]

The supernets are trained once into the cache. Each repetition draws a new set of random candidates
(seed 15 + repetition) and evaluates both supernets on every one of them.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import torch
from scipy.stats import kendalltau

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _fidelity import estimate  # noqa: E402
from _labels import recipe, score, standalone  # noqa: E402
from harness import Bench, interleave  # noqa: E402

from explorer.data import open_dataset  # noqa: E402
from explorer.space import SearchSpace, paper_candidate, paper_nee_candidate  # noqa: E402
from explorer.study.evaluators import SupernetEvaluator  # noqa: E402
from explorer.study.search import SearchConfig  # noqa: E402
from explorer.supernet import default_path, train_supernet  # noqa: E402
TEACHERS = ("max", "cycle")


def supernet_evaluators(space: SearchSpace, steps: int) -> dict:
    cfg = SearchConfig(study="bench")
    files = {}
    for teacher in TEACHERS:
        rec = dataclasses.replace(cfg.supernet_recipe(), steps=steps, teacher_depths=teacher)
        files[teacher] = default_path(space, cfg.data, rec)
        print(f"supernet teacher_depths={teacher}: {files[teacher]}", flush=True)
        train_supernet(space, cfg.data, rec, files[teacher])
    calib = open_dataset(cfg.data, "train", (64, 64), train_augment=False)
    val = open_dataset(cfg.data, "val", (64, 64), train_augment=False)
    return {t: SupernetEvaluator(f, space, calib, val, torch.device("cpu"), val_limit=cfg.val_limit)
            for t, f in files.items()}


def encoder_order(rows: list) -> str:
    """Each ranking's order of the best stand-alone candidate of every image encoder."""
    encoders = sorted({(c.encoder_blocks, c.width_mult) for c, *_ in rows})
    best = {e: min((r for r in rows if (r[0].encoder_blocks, r[0].width_mult) == e), key=lambda r: r[2])
            for e in encoders}
    lines = []
    for t in ["stand-alone", *TEACHERS]:
        ranked = sorted(best, key=lambda e: best[e][2] if t == "stand-alone" else best[e][1][t])
        lines.append(f"{t}: " + " > ".join(f"{b}x{w}" for b, w in ranked))
    return "; ".join(lines)


if __name__ == "__main__":
    bench = Bench(__file__, "Supernet rank fidelity by sandwich teacher depths", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=400, help="supernet steps")
    ap.add_argument("--candidates", type=int, default=16)
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    space = SearchSpace.from_yaml("anytime_depth")
    evaluators = supernet_evaluators(space, args.steps)
    for t in TEACHERS:
        bench.figure(f"tau_{t}", f"teacher_depths={t}: Kendall tau against stand-alone", "", "higher")
    for rep in bench.repetitions():
        rows = []
        for c in [paper_candidate(), paper_nee_candidate()] + space.random_candidates(args.candidates, seed=15 + rep):
            long = score(standalone(c, recipe(600)))
            est = interleave({t: (lambda ev=ev: estimate(ev, c)) for t, ev in evaluators.items()}, len(rows))
            rows.append((c, est, long))
            print(f"  {c.key} {c.encoder_blocks}x{c.width_mult}: stand-alone {long:.4f}  "
                  + "  ".join(f"{t} {v:.4f}" for t, v in est.items()), flush=True)
        for t in TEACHERS:
            bench.add(f"tau_{t}", kendalltau([r[1][t] for r in rows], [r[2] for r in rows]).statistic)
        print(f"  best of each image encoder, best first: {encoder_order(rows)}")
    bench.note(f"supernets of {args.steps} steps; {args.candidates} random candidates and 2 paper designs a repetition")
    bench.finish()
