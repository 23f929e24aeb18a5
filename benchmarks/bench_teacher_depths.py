"""Rank fidelity of supernets trained with each sandwich variant (``teacher_depths``: the label-trained
subnet always the deepest, ``max``, or turning over the encoder depths, ``cycle``) against the same
stand-alone labels: 16 random default-space candidates and the paper design with and without early
exits, each trained alone 600 steps (4x the proxy; cached in benchmarks/_labels), tx2, U(0, 33 ms).
Also each supernet's estimate of the best candidate of every image encoder among them against its
stand-alone loss, which is where the sandwich's bias showed.

    .venv/bin/python benchmarks/bench_teacher_depths.py [--steps 400] [--candidates 16]

The supernets are trained once into the cache (the `max` one is what searches made before the change).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch
from scipy.stats import kendalltau

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _labels import recipe, score, standalone  # noqa: E402

from explorer.anytime import anytime_loss  # noqa: E402
from explorer.cost import candidate_cost, get_device  # noqa: E402
from explorer.data import open_dataset  # noqa: E402
from explorer.study.evaluators import SupernetEvaluator  # noqa: E402
from explorer.study.search import SearchConfig  # noqa: E402
from explorer.space import SearchSpace, paper_candidate, paper_nee_candidate  # noqa: E402
from explorer.supernet import default_path, train_supernet  # noqa: E402

BUDGET = "time:uniform:33ms"

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=400, help="supernet steps (a fresh make search on a 2-core "
                    "machine trains 400-600, by its speed)")
    ap.add_argument("--candidates", type=int, default=16)
    args = ap.parse_args()
    torch.set_num_threads(2)
    space = SearchSpace.from_yaml("anytime_depth")
    cfg = SearchConfig(study="bench")
    files = {}
    for teacher in ("max", "cycle"):
        rec = dataclasses.replace(cfg.supernet_recipe(), steps=args.steps, teacher_depths=teacher)
        files[teacher] = default_path(space, cfg.data, rec)
        print(f"supernet teacher_depths={teacher}: {files[teacher]}", flush=True)
        train_supernet(space, cfg.data, rec, files[teacher])
    calib = open_dataset(cfg.data, "train", (64, 64), train_augment=False)
    val = open_dataset(cfg.data, "val", (64, 64), train_augment=False)
    evaluators = {t: SupernetEvaluator(f, space, calib, val, torch.device("cpu"), val_limit=cfg.val_limit)
                  for t, f in files.items()}
    tx2 = get_device("tx2")
    rows = []
    for c in [paper_candidate(), paper_nee_candidate()] + space.random_candidates(args.candidates, seed=15):
        long = score(standalone(c, recipe(600)))
        est = {t: anytime_loss(candidate_cost(c).path_costs(tx2, "time"), list(ev(c).metrics["rmse"]), BUDGET)
               for t, ev in evaluators.items()}
        rows.append((c, est, long))
        print(f"  {c.key} {c.encoder_blocks}x{c.width_mult}: stand-alone {long:.4f}  " +
              "  ".join(f"{t} {v:.4f}" for t, v in est.items()), flush=True)
    labels = [r[2] for r in rows]
    for t in files:
        tau = kendalltau([r[1][t] for r in rows], labels).statistic
        print(f"teacher_depths={t}: Kendall tau {tau:.2f} over {len(rows)} candidates")
    encoders = sorted({(c.encoder_blocks, c.width_mult) for c, *_ in rows})
    print("best stand-alone candidate of each image encoder, and its rank among those (1 = best):")
    best = {e: min((r for r in rows if (r[0].encoder_blocks, r[0].width_mult) == e), key=lambda r: r[2])
            for e in encoders}
    order = sorted(best, key=lambda e: best[e][2])
    for t in ["stand-alone", *files]:
        ranked = order if t == "stand-alone" else sorted(best, key=lambda e: best[e][1][t])
        print(f"  {t:12s} " + " > ".join(f"{b}x{w}" for b, w in ranked))
