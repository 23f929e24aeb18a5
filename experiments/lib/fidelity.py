"""Rank fidelity pieces shared by the benchmarks that score an estimate against stand-alone labels
(bench_fidelity, bench_supernet, bench_teacher_depths): the candidate set, the label recipes, the
label jobs (cached by _labels.py, several worker processes may fill the cache at once), the
supernet estimate of a candidate, and the rank figures (Kendall tau, Spearman, top-k recall)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch
from scipy.stats import kendalltau, spearmanr

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.space import Candidate, SearchSpace
from explorer.study.config import BASELINES, SearchConfig
from explorer.training.train import TrainConfig

from experiments.lib.labels import BUDGET, CACHE_DIR, cached, locked_file, score, standalone

#: the seed of the benchmark's random set (drawn by the space's own sampler)
CANDIDATE_SEED = 45
LABEL_SEEDS = (0, 1)
LONG_FACTOR = 4     # the long labels' recipe: the finalists' recipe this many times longer


def fidelity_candidates(space: SearchSpace, count: int) -> list[Candidate]:
    """``count`` random candidates of ``space`` (a fixed seed, the space's sampler: head kinds, encoder
    exits, LiDAR-only paths and stage orders in the space's proportions), then the baselines."""
    return space.random_candidates(count, seed=CANDIDATE_SEED) + [make() for make in BASELINES.values()]


def label_recipes(config: SearchConfig | None = None) -> dict[str, TrainConfig]:
    """{"proxy": the search's 150-step recipe (no pruning), "finalist": the finalists' recipe,
    "long": the finalists' recipe LONG_FACTOR times longer}, each at seed 0."""
    config = config or SearchConfig(study="fidelity")
    finalist = config.finalist_config(seed=0)
    return {"proxy": dataclasses.replace(config.train_config(), eval_every=0, seed=0),
            "finalist": finalist,
            "long": dataclasses.replace(finalist, steps=finalist.steps * LONG_FACTOR)}


def label_jobs(cands: list[Candidate], seeds=LABEL_SEEDS) -> list[tuple[Candidate, TrainConfig]]:
    """Every (candidate, recipe) the benchmark needs, the most telling first (a run cut short still
    leaves whole figures): the long and finalists' recipes at the first seed, the proxy, then the
    other seeds."""
    rec = label_recipes()
    jobs = []
    for i, seed in enumerate(seeds):
        for name in ("long", "finalist"):
            jobs += [(c, dataclasses.replace(rec[name], seed=seed)) for c in cands]
        if i == 0:
            jobs += [(c, rec["proxy"]) for c in cands]
    return jobs


def run_label_jobs(jobs: list, worker: int = 0) -> None:
    """Trains every job not cached yet; workers share the list by claiming a job with a file (a job a
    dead worker claimed is taken over once its claim is older than an hour)."""
    claims = CACHE_DIR / "claims"
    claims.mkdir(parents=True, exist_ok=True)
    import time
    for n, (cand, cfg) in enumerate(jobs):
        if cached(cand, cfg) is not None:
            continue
        claim = claims / f"{cand.key}-{cfg.steps}-{cfg.seed}"
        try:
            fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            os.close(fd)
        except FileExistsError:
            if time.time() - claim.stat().st_mtime < 3600:
                continue
        entry = standalone(cand, cfg)
        print(f"[worker {worker}] {n + 1}/{len(jobs)} {cand.key} {cfg.steps} steps seed {cfg.seed}: "
              f"{score(entry):.4f} in {entry['seconds']:.0f} s", flush=True)
        claim.unlink(missing_ok=True)


def labels_of(cand: Candidate, name: str, seeds=LABEL_SEEDS) -> list[float]:
    """The anytime losses (tx2, BUDGET) of ``cand`` under label recipe ``name``, one per cached seed."""
    cfg = label_recipes()[name]
    seeds = (0,) if name == "proxy" else seeds
    entries = [cached(cand, dataclasses.replace(cfg, seed=s)) for s in seeds]
    return [score(e) for e in entries if e is not None]


def estimate(evaluator, cand: Candidate) -> float:
    """The anytime loss (tx2, BUDGET) of ``cand`` as ``evaluator`` (a study evaluator) estimates it."""
    costs = candidate_cost(cand).path_costs(get_device("tx2"), "time")
    return anytime_loss(costs, list(evaluator(cand).metrics["rmse"]), BUDGET)


def estimates(file: Path, cands: list[Candidate], space: SearchSpace, calibration_images: int = 256,
              config: SearchConfig | None = None) -> dict[Candidate, float]:
    """The supernet estimate of every one of ``cands`` in the space, cached per supernet file (its name and
    size and time: a supernet trained again is estimated again), recalibration frames and candidate in
    ``estimates.json`` beside the labels: a benchmark run after the supernet is trained finds them,
    however many labels exist by then."""
    import json
    config = config or SearchConfig(study="fidelity")
    file = Path(file)
    stat = file.stat()
    tag = f"{file.stem}|{stat.st_size}|{stat.st_mtime_ns}|{calibration_images}|{config.val_limit}"
    cache_file = CACHE_DIR / "estimates.json"
    cache = json.loads(cache_file.read_text()) if cache_file.is_file() else {}
    inside = [c for c in cands if space.contains(c)]
    missing = [c for c in inside if f"{tag}|{c.key}" not in cache]
    if missing:
        evaluator = supernet_evaluator(file, space, config, calibration_images=calibration_images)
        new = {f"{tag}|{c.key}": estimate(evaluator, c) for c in missing}
        CACHE_DIR.mkdir(parents=True, exist_ok=True)
        with locked_file(cache_file):
            cache = json.loads(cache_file.read_text()) if cache_file.is_file() else {}
            cache.update(new)
            tmp = cache_file.with_suffix(f".tmp{os.getpid()}")
            tmp.write_text(json.dumps(cache, indent=1))
            tmp.replace(cache_file)
    return {c: cache[f"{tag}|{c.key}"] for c in inside}


def fine_tuned_estimate(evaluator, cand: Candidate, steps: int, config: SearchConfig | None = None,
                        lr_scale: float = 0.1) -> float:
    """The anytime loss of ``cand``'s slice of the supernet after ``steps`` steps of stand-alone training
    (the finalists' recipe at ``lr_scale`` times its learning rate), on the search's validation frames."""
    from explorer.data import open_dataset
    from explorer.training.train import train
    config = config or SearchConfig(study="fidelity")
    cfg = dataclasses.replace(config.finalist_config(seed=0), steps=steps, lr=config.lr * lr_scale,
                              lr_end=config.lr * lr_scale / 10)
    net = evaluator.supernet.extract(cand)
    tr = open_dataset(config.data, "train", config.train_size, seed=0)
    va = open_dataset(config.data, "val", config.train_size, train_augment=False)
    res = train(net, tr, va, cfg, val_limit=config.val_limit)
    costs = candidate_cost(cand).path_costs(get_device("tx2"), "time")
    return anytime_loss(costs, [float(x) for x in res.metrics["rmse"]], BUDGET)


def top_recall(estimates: list[float], labels: list[float], k: int = 5, within: int = 10) -> int:
    """How many of the labels' best ``k`` are among the estimate's best ``within`` (lower is better)."""
    best = set(sorted(range(len(labels)), key=labels.__getitem__)[:k])
    picked = set(sorted(range(len(estimates)), key=estimates.__getitem__)[:within])
    return len(best & picked)


def rank_figures(estimates: list[float], labels: list[float]) -> dict[str, float]:
    """Kendall tau, Spearman and top-5-in-10 recall of ``estimates`` against ``labels`` (the recall only
    over more than 10 candidates: with fewer, every one is in the best 10)."""
    figs = {"tau": float(kendalltau(estimates, labels).statistic),
            "spearman": float(spearmanr(estimates, labels).statistic)}
    if len(labels) > 10:
        figs["recall"] = float(top_recall(estimates, labels))
    return figs


def supernet_evaluator(file: Path, space: SearchSpace, config: SearchConfig | None = None, **kw):
    """The search's supernet evaluator over ``file`` (its validation frames, BatchNorm recalibration)."""
    from explorer.data import open_dataset
    from explorer.supernet.evaluators import SupernetEvaluator
    config = config or SearchConfig(study="fidelity")
    calib = open_dataset(config.data, "train", config.train_size, train_augment=False)
    val = open_dataset(config.data, "val", config.train_size, train_augment=False)
    return SupernetEvaluator(file, space, calib, val, torch.device("cpu"), **{"val_limit": config.val_limit, **kw})
