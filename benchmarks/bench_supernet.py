"""The supernet evaluator: training time and peak memory, candidates evaluated per 10 minutes, and
rank fidelity against stand-alone training with a 4x longer recipe (proxy's tau beside it).

    ANYTIME_EXPLORER_CACHE=... .venv/bin/python benchmarks/bench_supernet.py [--candidates 16]

Stand-alone results are cached in reports/bench/ (benchmarks/_labels.py): a rerun only pays for the
supernet side. The supernet is the one `explorer search` uses by default (trained here if missing).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
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
from explorer.space import (SearchSpace, fastdepth_candidate, paper_candidate,  # noqa: E402
                            paper_nee_candidate)
from explorer.supernet import default_path, read_supernet, train_supernet  # noqa: E402

BUDGET = "time:uniform:33ms"


def label_candidates(space: SearchSpace, n: int) -> list:
    """The three baselines and ``n`` random candidates of the default space (FastDepth-like lies
    outside it: the supernet cannot estimate it, the proxy can)."""
    return [paper_candidate(), paper_nee_candidate(), fastdepth_candidate()] + space.random_candidates(n, seed=15)


def peak_memory_of_training(steps: int) -> tuple[float, float]:
    """(seconds per step after the first two, peak RSS in MiB) of a fresh process training the supernet
    ``steps`` steps (start-up, data loading and the first steps' warm-up are left out of the time)."""
    code = ("import time, torch, tempfile; from explorer.space import SearchSpace; "
            "from explorer.supernet import SupernetRecipe, train_supernet; "
            f"r = SupernetRecipe(steps={steps}); t = {{}}; "
            "train_supernet(SearchSpace.from_yaml('anytime_depth'), 'synthetic', r, tempfile.mkdtemp() + '/s.pt', "
            "progress=lambda s, n, rec: t.setdefault(s, time.perf_counter())); "
            "print((t[r.steps] - t[2]) / (r.steps - 2))")
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return float(out.stdout.strip().splitlines()[-1]), max(peak, before) / 1024


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--candidates", type=int, default=16, help="random default-space candidates (plus 3 baselines)")
    ap.add_argument("--throughput", type=int, default=20, help="candidates per throughput repetition")
    ap.add_argument("--val-limit", type=int, default=96, help="validation frames per candidate, as in a search")
    ap.add_argument("--fidelity-only", action="store_true", help="skip the training and throughput timings")
    ap.add_argument("--replay", default="", help="time the candidates of this study.db (a search's own sequence) "
                    "instead of random ones")
    ap.add_argument("--memo-gib", type=float, default=None, help="stage memo size of the stagewise evaluator")
    ap.add_argument("--skip-fidelity", action="store_true", help="only the training and throughput timings")
    ap.add_argument("--calibration-sweep", default="", help="also the supernet's tau with these BatchNorm "
                    "calibration frame counts, e.g. 16,64,256,1024 (the search uses 256)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    space = SearchSpace.from_yaml("anytime_depth")
    cfg = SearchConfig(study="bench")
    sn_recipe = cfg.supernet_recipe()
    file = default_path(space, cfg.data, sn_recipe)
    if not file.is_file() or not read_supernet(file).get("complete"):
        print(f"training the supernet ({sn_recipe.steps} steps) into {file}", flush=True)
        train_supernet(space, cfg.data, sn_recipe, file)
    state = read_supernet(file)
    print(f"supernet {file.name}: {state['step']} steps ({sn_recipe.random_subnets} random subnets + largest + "
          f"smallest per step, batch {sn_recipe.batch_size} at {sn_recipe.input_size[0]}x{sn_recipe.input_size[1]}), "
          f"trained in {state['seconds'] / 60:.1f} min (as recorded in the file)")

    # -- training: time per step and peak memory, 3 fresh processes -------------------------------
    reps = [] if args.fidelity_only else [peak_memory_of_training(12) for _ in range(3)]
    for i, (s, mb) in enumerate(reps, 1):
        print(f"  supernet training rep {i}: {s:.2f} s/step, peak RSS {mb:.0f} MiB")
    per_step = statistics.median(r[0] for r in reps) if reps else float("nan")
    if reps:
        print(f"supernet training: median {per_step:.2f} s/step -> {per_step * sn_recipe.steps / 60:.1f} min for "
              f"{sn_recipe.steps} steps; peak RSS {max(r[1] for r in reps):.0f} MiB")

    # -- throughput: candidates fully evaluated per 10 minutes ------------------------------------
    size = sn_recipe.input_size
    calib = open_dataset(cfg.data, "train", size, train_augment=False)
    val = open_dataset(cfg.data, "val", size, train_augment=False)
    # stage by stage, candidates share the stages they have in common (SupernetEvaluator(stagewise=True),
    # what a search uses); each repetition times the same candidates both ways, interleaved. Random
    # candidates share less than a search's, whose sampler keeps varying its best ones.
    memo = {} if args.memo_gib is None else {"memo_bytes": int(args.memo_gib * 2 ** 30)}
    evaluators = {shared: SupernetEvaluator(file, space, calib, val, torch.device("cpu"), val_limit=args.val_limit,
                                            stagewise=shared, **memo) for shared in (True, False)}
    tx2 = get_device("tx2")
    if not args.fidelity_only:
        t0 = time.perf_counter()
        for w in space.width_mult:
            evaluators[True].shared_encoder(w)
        print(f"  shared encoders of widths {space.width_mult} on {len(evaluators[True].calibration)} calibration "
              f"+ {len(evaluators[True].validation)} validation batches: {time.perf_counter() - t0:.1f} s, once per search")
    rates: dict[bool, list[float]] = {True: [], False: []}
    replay = []
    if args.replay:   # a finished study's candidates, in the order its sampler proposed them
        import optuna
        from explorer.space import Candidate
        storage = f"sqlite:///{Path(args.replay).resolve()}"
        study = optuna.load_study(study_name=optuna.get_all_study_names(storage)[0], storage=storage)
        replay = [Candidate.from_dict(t.user_attrs["candidate"]) for t in study.trials
                  if "candidate" in t.user_attrs and not t.user_attrs.get("baseline") and "duplicate_of" not in t.user_attrs]
        replay = [c for c in replay if space.contains(c)]
        print(f"  replaying {len(replay)} distinct candidates of {args.replay} in their order, in 3 slices")
    for rep in range(0 if args.fidelity_only else 3):
        if replay:
            n = len(replay) // 3
            cands = replay[rep * n:(rep + 1) * n]
        else:
            cands = space.random_candidates(args.throughput, seed=100 + rep)
        for shared, evaluator in evaluators.items():
            t0 = time.perf_counter()
            for c in cands:
                m = evaluator(c).metrics
                anytime_loss(candidate_cost(c).path_costs(tx2, "time"), list(m["rmse"]), BUDGET)
            per = (time.perf_counter() - t0) / len(cands)
            rates[shared].append(600 / per)
            print(f"  throughput rep {rep + 1}, {'stagewise' if shared else 'whole    '}: {per:.2f} s per "
                  f"candidate (extract, BN recalibration, {args.val_limit} validation frames, costing) -> "
                  f"{600 / per:,.0f} per 10 min")
    if rates[True]:
        memo = evaluators[True].memo
        print(f"throughput: median {statistics.median(rates[True]):,.0f} candidates per 10 minutes stage by stage "
              f"(the search's; {memo.hits} of {memo.hits + memo.misses} stages found evaluated, "
              f"{memo.nbytes / 2 ** 20:.0f} MiB kept), {statistics.median(rates[False]):,.0f} whole")
    if args.skip_fidelity:
        sys.exit(0)

    # -- fidelity: supernet and proxy against stand-alone training 4x longer than the proxy --------
    # the supernet side exactly as a search evaluates (its validation frames, BatchNorm recalibration)
    full = SupernetEvaluator(file, space, calib, val, torch.device("cpu"), val_limit=cfg.val_limit)
    proxy_cfg, long_cfg = recipe(150), recipe(600)
    rows = []
    for c in label_candidates(space, args.candidates):
        long = score(standalone(c, long_cfg))
        prox = score(standalone(c, proxy_cfg))
        est = None
        if space.contains(c):
            m = full(c).metrics
            est = anytime_loss(candidate_cost(c).path_costs(tx2, "time"), list(m["rmse"]), BUDGET)
        rows.append((c, est, prox, long))
        print(f"  {c.key}: supernet {'   n/a' if est is None else f'{est:.4f}'}  proxy {prox:.4f}  "
              f"stand-alone x4 {long:.4f}  {c.describe()[:90]}")
    both = [r for r in rows if r[1] is not None]
    tau_s = kendalltau([r[1] for r in both], [r[3] for r in both]).statistic
    tau_p = kendalltau([r[2] for r in both], [r[3] for r in both]).statistic
    tau_p_all = kendalltau([r[2] for r in rows], [r[3] for r in rows]).statistic
    print(f"rank fidelity vs stand-alone {long_cfg.steps} steps (tx2, {BUDGET}), {len(both)} candidates in the "
          f"space: supernet Kendall tau {tau_s:.2f}; proxy ({proxy_cfg.steps} steps) {tau_p:.2f} "
          f"(proxy over all {len(rows)} incl. FastDepth: {tau_p_all:.2f})")
    for n in [int(x) for x in args.calibration_sweep.split(",") if x]:
        sweep = SupernetEvaluator(file, space, calib, val, torch.device("cpu"), val_limit=cfg.val_limit,
                                  calibration_images=n)
        est = [anytime_loss(candidate_cost(c).path_costs(tx2, "time"), list(sweep(c).metrics["rmse"]), BUDGET)
               for c, *_ in both]
        print(f"  BatchNorm calibrated on {n} frames: supernet Kendall tau "
              f"{kendalltau(est, [r[3] for r in both]).statistic:.2f}")
    out = Path(__file__).resolve().parents[1] / "reports" / "bench" / "supernet.json"
    out.write_text(json.dumps({"tau_supernet": tau_s, "tau_proxy": tau_p, "rates": rates[True], "rates_unshared": rates[False], "per_step": per_step,
                               "rows": [(c.key, e, p, l) for c, e, p, l in rows]}, indent=1))
