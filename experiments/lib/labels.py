"""Stand-alone training results shared by the benchmarks that train candidates (supernet, search,
exit weights, residual exits, teacher depths): each (candidate, recipe, seed) is trained once and
cached in a JSON file (``ANYTIME_BENCH_CACHE``, default reports/bench/), so a benchmark can be rerun
(or resumed after a kill) without paying for the trainings again."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import time
from pathlib import Path

import torch

from explorer.anytime import anytime_loss
from explorer.cost import candidate_cost, get_device
from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import Candidate
from explorer.study import trial_record
from explorer.training.train import TrainConfig, train

CACHE_DIR = Path(os.environ.get("ANYTIME_BENCH_CACHE") or Path(__file__).resolve().parents[1] / "reports" / "bench")
BUDGET = "time:uniform:33ms"


def recipe(steps: int, size=(64, 64), seed: int = 0) -> TrainConfig:
    """The search's proxy recipe (AdamW, lr 2e-3 -> 2e-4, batch 16), with ``steps`` steps."""
    return TrainConfig(steps=steps, batch_size=16, input_size=tuple(size), lr=2e-3, lr_end=2e-4, seed=seed)


#: TrainConfig fields added after results were first cached: left out of the key at these values
_LATER_DEFAULTS = {"supervision": "supervised", "poses": "net", "scan_loss": True}


def _cache(steps: int) -> Path:
    return CACHE_DIR / f"standalone-{steps}.json"


def _load(steps: int) -> dict:
    f = _cache(steps)
    return json.loads(f.read_text()) if f.is_file() else {}


def _key(candidate: Candidate, cfg: TrainConfig, data: str, val_limit: int | None) -> str:
    recipe_dict = {k: v for k, v in cfg.to_dict().items() if k not in _LATER_DEFAULTS or v != _LATER_DEFAULTS[k]}
    return f"{candidate.key}|{data}|{json.dumps(recipe_dict, sort_keys=True)}|{val_limit}"


def standalone(candidate: Candidate, cfg: TrainConfig, data: str = "synthetic", device: str = "tx2",
               val_limit: int | None = None) -> dict:
    """Per-path RMSE and the anytime loss (tx2, U(0, 33 ms)) of ``candidate`` trained alone with ``cfg``."""
    key = _key(candidate, cfg, data, val_limit)
    cache = _load(cfg.steps)
    if key in cache:
        return cache[key]
    torch.manual_seed(cfg.seed)
    net = build_network(candidate)
    tr = open_dataset(data, "train", cfg.input_size, seed=cfg.seed)
    va = open_dataset(data, "val", cfg.input_size, train_augment=False)
    t0 = time.perf_counter()
    res = train(net, tr, va, cfg, val_limit=val_limit)
    rmse = [float(x) for x in res.metrics["rmse"]]
    # costs are applied when read (score()), so a refitted profile never leaves stale values here
    entry = {"candidate": candidate.to_dict(), "rmse": rmse, "seconds": time.perf_counter() - t0,
             "steps": cfg.steps, "seed": cfg.seed}
    with _locked(cfg.steps):   # several processes may fill the same cache (bench_fidelity --workers)
        cache = _load(cfg.steps)
        cache[key] = entry
        tmp = _cache(cfg.steps).with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(cache, indent=1))
        tmp.replace(_cache(cfg.steps))
    return entry


def _locked(steps: int):
    return locked_file(_cache(steps))


@contextlib.contextmanager
def locked_file(path: Path):
    """Holds an exclusive lock beside ``path`` (its read-modify-write by one process at a time)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(Path(path).with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def cached(candidate: Candidate, cfg: TrainConfig, data: str = "synthetic", val_limit: int | None = None
           ) -> dict | None:
    """The stored result of :func:`standalone` for these arguments, or None (nothing is trained)."""
    return _load(cfg.steps).get(_key(candidate, cfg, data, val_limit))


def score(entry: dict, device: str = "tx2", budget: str = BUDGET) -> float:
    """The anytime loss of a stored result on ``device`` for ``budget``."""
    cand = Candidate.from_dict(entry["candidate"])
    return anytime_loss(candidate_cost(cand).path_costs(get_device(device), "time"), entry["rmse"], budget)


def with_seed(cfg: TrainConfig, seed: int) -> TrainConfig:
    return dataclasses.replace(cfg, seed=seed)


def add_candidate_options(ap, steps: int = 600) -> None:
    """--candidate / --study / --reports / --steps, as benchmarks that train the paper design beside one
    other candidate take them (their repetitions, --reps, are training seeds)."""
    ap.add_argument("--candidate", help="a candidate YAML (as the report gives each network, or as "
                    "`explorer train` takes)")
    ap.add_argument("--study", help="take the study's winner as the candidate")
    ap.add_argument("--reports", default="reports")
    ap.add_argument("--steps", type=int, default=steps)


def candidates_of(args) -> dict[str, Candidate]:
    """{"paper": the paper design} and the candidate ``add_candidate_options`` named (if any), as
    "candidate" or "winner" (keys usable in figure names)."""
    from explorer.space import paper_candidate
    cands = {"paper": paper_candidate()}
    if args.candidate:
        cands["candidate"] = Candidate.from_yaml(args.candidate)
    elif args.study:
        from explorer.study.results import winner
        from explorer.study.storage import load_study
        win = winner(load_study(args.study, None, Path(args.reports)))
        cands["winner"] = Candidate.from_dict(trial_record(win).candidate)
    return cands
