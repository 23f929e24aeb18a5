"""The supernet evaluator: training time per step and peak memory, candidates evaluated per 10 minutes
(stage by stage, as a search evaluates, and whole), and rank fidelity against stand-alone training
with a 4x longer recipe (the proxy recipe's beside it). A search's reach is its throughput, and its
worth the supernet's ranking.

    ANYTIME_EXPLORER_CACHE=... python benchmarks/bench_supernet.py [--reps 3] [--candidates 16]
        [--throughput 20] [--fidelity-only | --skip-fidelity] [--replay study.db] [--calibration-sweep 16,64,256]

The supernet is the one ``explorer search`` uses by default (trained here if missing). Each repetition
trains a few steps in a fresh process (time and peak memory) and evaluates a new set of candidates both
ways, in an order that rotates. Fidelity is measured once (one value per figure) over the three
baselines and --candidates random ones; stand-alone results are cached (benchmarks/_labels.py).
"""

from __future__ import annotations

import resource
import subprocess
import sys
import time
from pathlib import Path

import torch
from scipy.stats import kendalltau

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _fidelity import estimate  # noqa: E402
from _labels import BUDGET, recipe, score, standalone  # noqa: E402
from harness import Bench, interleave  # noqa: E402

from explorer.anytime import anytime_loss  # noqa: E402
from explorer.cost import candidate_cost, get_device  # noqa: E402
from explorer.data import open_dataset  # noqa: E402
from explorer.space import (SearchSpace, fastdepth_candidate, paper_candidate,  # noqa: E402
                            paper_nee_candidate)
from explorer.study.evaluators import SupernetEvaluator  # noqa: E402
from explorer.study.search import SearchConfig  # noqa: E402
from explorer.supernet import default_path, read_supernet, train_supernet  # noqa: E402
from explorer.study import trial_record  # noqa: E402


def label_candidates(space: SearchSpace, n: int) -> list:
    """The three baselines and ``n`` random candidates of the default space (FastDepth-like lies
    outside it: the supernet cannot estimate it, the proxy can)."""
    return [paper_candidate(), paper_nee_candidate(), fastdepth_candidate()] + space.random_candidates(n, seed=15)


def training_step(steps: int) -> tuple[float, float]:
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


def replayed(study_file: str, space: SearchSpace) -> list:
    """A finished study's distinct candidates in the order its sampler proposed them."""
    import optuna
    from explorer.space import Candidate
    storage = f"sqlite:///{Path(study_file).resolve()}"
    study = optuna.load_study(study_name=optuna.get_all_study_names(storage)[0], storage=storage)
    cands = [Candidate.from_dict(trial_record(t).candidate) for t in study.trials
             if trial_record(t).candidate and not trial_record(t).baseline and trial_record(t).duplicate_of is None]
    return [c for c in cands if space.contains(c)]


def per_candidate_s(evaluator, cands, tx2) -> float:
    """Seconds per candidate fully evaluated: extract, BN recalibration, validation frames, costing."""
    t0 = time.perf_counter()
    for c in cands:
        anytime_loss(candidate_cost(c).path_costs(tx2, "time"), list(evaluator(c).metrics["rmse"]), BUDGET)
    return (time.perf_counter() - t0) / len(cands)


def fidelity(bench: Bench, space, make_evaluator, calibration_sweep: list[int]) -> None:
    """Kendall tau of the supernet's and the proxy's anytime losses against stand-alone training 4x
    longer than the proxy (one value each)."""
    full = make_evaluator()   # exactly as a search evaluates (its validation frames, BatchNorm recalibration)
    proxy_cfg, long_cfg = recipe(150), recipe(600)
    rows = []
    for c in label_candidates(space, bench.args.candidates):
        long, prox = score(standalone(c, long_cfg)), score(standalone(c, proxy_cfg))
        est = estimate(full, c) if space.contains(c) else None
        rows.append((c, est, prox, long))
        print(f"  {c.key}: supernet {'   n/a' if est is None else f'{est:.4f}'}  proxy {prox:.4f}  "
              f"stand-alone x4 {long:.4f}  {c.describe()[:90]}", flush=True)
    both = [r for r in rows if r[1] is not None]
    labels = [r[3] for r in both]
    for name, label, value in (
            ("tau_supernet", "supernet Kendall tau against stand-alone", kendalltau([r[1] for r in both], labels)),
            ("tau_proxy", "proxy Kendall tau against stand-alone", kendalltau([r[2] for r in both], labels)),
            ("tau_proxy_all", "proxy Kendall tau, FastDepth included",
             kendalltau([r[2] for r in rows], [r[3] for r in rows]))):
        bench.add(bench.figure(name, label, "", "higher"), value.statistic)
    for n in calibration_sweep:
        sweep = make_evaluator(calibration_images=n)
        est = [estimate(sweep, c) for c, *_ in both]
        bench.add(bench.figure(f"tau_supernet_calib{n}", f"supernet Kendall tau, BatchNorm calibrated on {n} frames",
                               "", "higher"), kendalltau(est, labels).statistic)
    bench.note(f"fidelity over {len(both)} candidates in the space ({len(rows)} with FastDepth), stand-alone "
               f"{long_cfg.steps} steps, proxy {proxy_cfg.steps} steps, tx2 {BUDGET}")


def throughput_rep(bench: Bench, rep: int, evaluators: dict, cands: list, tx2) -> None:
    per = interleave({k: (lambda e=e: per_candidate_s(e, cands, tx2)) for k, e in evaluators.items()}, rep)
    for k, s in per.items():
        bench.add(f"{k}_per_10min", 600 / s)


if __name__ == "__main__":
    bench = Bench(__file__, "Supernet evaluator: training, throughput and rank fidelity", __doc__)
    ap = bench.parser()
    ap.add_argument("--candidates", type=int, default=16, help="random default-space candidates (plus 3 baselines)")
    ap.add_argument("--throughput", type=int, default=20, help="candidates per throughput repetition")
    ap.add_argument("--val-limit", type=int, default=96, help="validation frames per candidate, as in a search")
    ap.add_argument("--fidelity-only", action="store_true", help="skip the training and throughput timings")
    ap.add_argument("--skip-fidelity", action="store_true", help="only the training and throughput timings")
    ap.add_argument("--replay", default="", help="time the candidates of this study.db (a search's own sequence, "
                    "in --reps slices) instead of random ones")
    ap.add_argument("--memo-gib", type=float, default=None, help="stage memo size of the stagewise evaluator")
    ap.add_argument("--calibration-sweep", default="", help="also the supernet's tau with these BatchNorm "
                    "calibration frame counts, e.g. 16,64,256,1024 (the search uses 256)")
    args = bench.parse_args(ap)
    torch.set_num_threads(2)
    space = SearchSpace.from_yaml("anytime_depth")
    cfg = SearchConfig(study="bench")
    sn_recipe = cfg.supernet_recipe()
    file = default_path(space, cfg.data, sn_recipe)
    if not file.is_file() or not read_supernet(file).get("complete"):
        print(f"training the supernet ({sn_recipe.steps} steps) into {file}", flush=True)
        train_supernet(space, cfg.data, sn_recipe, file)
    state = read_supernet(file)
    bench.note(f"supernet {file.name}: {state['step']} steps ({sn_recipe.random_subnets} random subnets + largest + "
               f"smallest per step, batch {sn_recipe.batch_size} at {sn_recipe.input_size[0]}x"
               f"{sn_recipe.input_size[1]}), trained in {state['seconds'] / 60:.1f} min (as recorded in the file)")
    size = sn_recipe.input_size
    calib = open_dataset(cfg.data, "train", size, train_augment=False)
    val = open_dataset(cfg.data, "val", size, train_augment=False)

    def make_evaluator(**kw):
        return SupernetEvaluator(file, space, calib, val, torch.device("cpu"), **{"val_limit": cfg.val_limit, **kw})
    if not args.fidelity_only:
        memo = {} if args.memo_gib is None else {"memo_bytes": int(args.memo_gib * 2 ** 30)}
        # stage by stage, candidates share the stages they have in common (what a search uses)
        evaluators = {"stagewise": make_evaluator(val_limit=args.val_limit, stagewise=True, **memo),
                      "whole": make_evaluator(val_limit=args.val_limit, stagewise=False)}
        for w in space.width_mult:   # once per search: left out of the throughput
            evaluators["stagewise"].shared_encoder(w)
        replay = replayed(args.replay, space) if args.replay else []
        tx2 = get_device("tx2")
        bench.figure("train_step_s", "supernet training, seconds a step", "s", "lower")
        bench.figure("train_peak_mib", "supernet training, peak RSS", "MiB", "lower")
        bench.figure("stagewise_per_10min", "candidates per 10 minutes, stage by stage (the search's)", "", "higher")
        bench.figure("whole_per_10min", "candidates per 10 minutes, whole", "", "higher")
        for rep in bench.repetitions():
            s, mib = training_step(12)
            bench.add("train_step_s", s)
            bench.add("train_peak_mib", mib)
            n = len(replay) // args.reps
            cands = (replay[rep * n:(rep + 1) * n] if replay
                     else space.random_candidates(args.throughput, seed=100 + rep))
            throughput_rep(bench, rep, evaluators, cands, tx2)
        m = evaluators["stagewise"].memo
        bench.note(f"stage memo: {m.hits} of {m.hits + m.misses} stages found evaluated, {m.nbytes / 2 ** 20:.0f} MiB "
                   f"kept; {args.val_limit} validation frames a candidate")
    if not args.skip_fidelity:
        fidelity(bench, space, make_evaluator, [int(x) for x in args.calibration_sweep.split(",") if x])
    bench.finish()
