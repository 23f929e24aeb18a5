"""Whole commands as a user runs them: wall time and memory.

    python -m benchmarks.commands --list
    python -m benchmarks.commands --only NAME [its options]
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
import os
import random
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import optuna

from explorer.data import open_dataset
from explorer.space import SearchSpace
from explorer.study import trial_record
from explorer.study.config import SearchConfig
from explorer.study.finalists import finalist_trials, retrain_finalists
from explorer.study.results import is_retrained, scored_trials, unbeaten_baseline, winner
from explorer.study.storage import load_study

from benchmarks.harness import Bench, Case, ROOT, image_size, rotated, run_suite


# -- search_memory ----------------------------------------------------------------------------

SAMPLE_S = 0.2


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            kids.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry))
    return kids


def _rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def tree_rss(root: int) -> int:
    """The summed RSS of ``root`` and every process below it (worker processes count too)."""
    kids, todo, total = _children(), [root], 0
    while todo:
        pid = todo.pop()
        total += _rss_bytes(pid)
        todo += kids.get(pid, [])
    return total


def run_sampled(cmd: list[str], cwd: Path, env: dict) -> tuple[int, float, float, float, str]:
    """(exit code, peak tree RSS in bytes, seconds into the run it was reached, wall seconds, output tail)."""
    log = cwd / "search.log"
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        t0, peak, peak_at = time.time(), 0, 0.0
        while proc.poll() is None:
            rss = tree_rss(proc.pid)
            if rss > peak:
                peak, peak_at = rss, time.time() - t0
            time.sleep(SAMPLE_S)
        wall = time.time() - t0
    tail = "\n".join(log.read_text(errors="replace").replace("\r", "\n").splitlines()[-12:])
    return proc.returncode, peak, peak_at, wall, tail


def generate_data(cache: Path) -> Path:
    """The default data set generated into ``cache`` (untimed); its file."""
    code = ("from explorer.data.synthetic import SyntheticConfig, ensure_synthetic; "
            "print(ensure_synthetic(SyntheticConfig()))")
    env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(cache)}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    return Path(out.stdout.strip().splitlines()[-1])


def one_run(bench: Bench, data: Path, limit_s: int, threads: int, rep: int) -> None:
    work = Path(tempfile.mkdtemp(prefix="bench-search-memory-"))
    try:
        cache = work / "cache"
        cache.mkdir()
        (cache / data.name).symlink_to(data)          # the data, not the supernet: that is trained anew
        env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(cache), "PYTHONUNBUFFERED": "1"}
        if threads:
            env["OMP_NUM_THREADS"] = str(threads)
        cmd = [sys.executable, "-m", "explorer", "search", "--device", "tx2", "--time-limit", str(limit_s)]
        code, peak, peak_at, wall, tail = run_sampled(cmd, work, env)
        print(f"  rep {rep}: exit {code}, {wall:.0f} s, peak {peak / 1e9:.2f} GB at {peak_at:.0f} s\n{tail}",
              flush=True)
        if code != 0:
            raise SystemExit(f"explorer search failed (exit {code}):\n{tail}")
        bench.add("peak_rss_gb", peak / 1e9)
        bench.add("peak_at", peak_at / wall)
        bench.add("wall_s", wall)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def bench_search_memory(argv: Sequence[str] | None = None) -> None:
    """Peak memory of `make search`'s job: ``explorer search --device tx2 --time-limit L`` on the embedded
    default data, each repetition in a fresh folder with a fresh cache (its supernet trained anew), the
    resident memory (RSS) of its whole process tree sampled every 0.2 s. A laptop with 8 GB must run it
    beside a desktop; the target is under 3 GB. The default data is generated once, before the
    repetitions (it takes a few minutes and little memory), so the limit goes to the phases that hold
    memory: measuring the machine (a few steps at 224x224), the supernet's training, sampling (the
    evaluator's stage memo and encoder features) and the finalists' retraining and tuning at 224x224.

        python -m benchmarks.commands --only search_memory [--reps 3] [--time-limit 700] [--threads 1]

    ``--time-limit 700`` is what `make search`'s 960 s leave after generating the data on a 2-core machine.
    About 12 minutes a repetition.
    """
    bench = Bench("bench_search_memory", "make search's peak memory (RSS of the process tree)",
                  bench_search_memory.__doc__)
    ap = bench.parser()
    ap.add_argument("--time-limit", type=int, default=700, help="the search's --time-limit in seconds")
    ap.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS for the search (0: as make search, "
                    "the free cores)")
    args = bench.parse_args(ap, argv)
    bench.figure("peak_rss_gb", "peak RSS of the search's process tree (target under 3 GB)", "GB", "lower")
    bench.figure("peak_at", "when the peak came, as a share of the run's wall time", "", None)
    bench.figure("wall_s", "the search's wall time", "s", None)
    data_dir = Path(tempfile.mkdtemp(prefix="bench-search-memory-data-"))
    try:
        t0 = time.time()
        data = generate_data(data_dir)
        print(f"default data generated in {time.time() - t0:.0f} s: {data}", flush=True)
        for rep in bench.repetitions():
            one_run(bench, data, args.time_limit, args.threads, rep)
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)
    peaks = bench.figures["peak_rss_gb"].reps
    print(f"peak RSS per repetition: {', '.join(f'{p:.2f}' for p in peaks)} GB; "
          f"median {statistics.median(peaks):.2f} GB")
    bench.note(f"explorer search --device tx2 --time-limit {args.time_limit} (make search's job; its 960 s less "
               f"the data's generation, done once before the repetitions), OMP_NUM_THREADS="
               f"{args.threads or 'unset'}, {os.cpu_count()} cores; RSS summed over the process tree every "
               f"{SAMPLE_S} s; the checkout's code ({ROOT.name}), a fresh cache and supernet each repetition")
    bench.finish()


# -- make_search_load -------------------------------------------------------------------------

STUDY = "tx2-anytime_depth"


def _spin() -> None:
    while True:
        pass


def _summary_is_honest(clone: Path, stdout: str) -> tuple[float, float, bool]:
    """(retrained winner / best retrained baseline, retrained winner / retrained paper design, whether the
    summary said what it had to)."""
    study = load_study(STUDY, None, clone / "reports")
    best = winner(study)
    bases = [t for t in scored_trials(study) if is_retrained(t) and trial_record(t).baseline]
    base = min(bases, key=lambda t: t.values[0], default=None)
    paper = next((t for t in bases if trial_record(t).baseline == "paper"), None)
    retrained_winner = best is not None and is_retrained(best)
    ratio = best.values[0] / base.values[0] if retrained_winner and base else math.nan
    to_paper = best.values[0] / paper.values[0] if retrained_winner and paper else math.nan
    unbeaten = unbeaten_baseline(study) is not None
    said = "no searched candidate beat" in stdout
    return ratio, to_paper, said == unbeaten and (ratio <= 1.0 or said)


def loaded_run(bench: Bench, loads: int, limit_s: float, rep: int, keep: Path | None) -> None:
    """One repetition; with ``keep``, its clone (study, data cache, .venv) stays in ``keep/rep-N``."""
    if keep:
        work = keep / f"rep-{rep}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
    else:
        work = Path(tempfile.mkdtemp(prefix="bench-make-search-"))
    try:
        clone = work / "clone"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        env = {**os.environ, "ANYTIME_EXPLORER_CACHE": str(work / "cache"), "SEARCH_LIMIT_S": str(int(limit_s))}
        spinners = [mp.get_context("fork").Process(target=_spin, daemon=True) for _ in range(loads)]
        for p in spinners:
            p.start()
        t0 = time.time()
        try:
            run = subprocess.run(["make", "search"], cwd=clone, env=env, capture_output=True, text=True)
        finally:
            for p in spinners:
                p.terminate()
        wall = time.time() - t0
        tail = "\n".join(run.stdout.splitlines()[-25:])
        print(f"  rep {rep}: make search exit {run.returncode}, {wall:.0f} s\n{tail}", flush=True)
        if run.returncode != 0:
            raise SystemExit(f"make search failed:\n{run.stderr[-2000:]}")
        ratio, to_paper, honest = _summary_is_honest(clone, run.stdout)
        bench.add("wall_s", wall)
        bench.add("over_limit", wall / limit_s)
        bench.add("winner_over_best_baseline", ratio)
        bench.add("winner_over_paper", to_paper)
        bench.add("summary_honest", 1.0 if honest else 0.0)
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def bench_make_search_load(argv: Sequence[str] | None = None) -> None:
    """`make search` as a new user runs it, on a machine that other work keeps busy: a fresh clone of the
    current commit, a fresh data and supernet cache, ``--loads`` CPU-bound processes running beside it
    from start to end. The figures: the wall time of the whole ``make search`` (setup included) against
    its 16-minute limit, whether the summary told the truth when no searched candidate beat a
    baseline after retraining (it must say so, not call the candidate a winner), and the study's own
    answer: its retrained winner's anytime loss over the retrained paper design's.

        python -m benchmarks.commands --only make_search_load [--loads 2] [--reps 3] [--limit-s 960] [--keep DIR]

    Each repetition clones, sets up its own .venv (pip's cache helps the later ones) and generates
    its own data, so that none of them starts warm. About 17 minutes a repetition.
    """
    bench = Bench("bench_make_search_load", "make search from a fresh clone under CPU-bound load: wall time against its limit",
                  bench_make_search_load.__doc__)
    ap = bench.parser()
    ap.add_argument("--loads", type=int, default=2, help="CPU-bound processes running beside it")
    ap.add_argument("--limit-s", type=float, default=960.0, help="make search's limit (SEARCH_LIMIT_S)")
    ap.add_argument("--keep", type=Path, help="keep each repetition's clone (its study in reports/, its data "
                    "cache) in KEEP/rep-N, for experiments.held_out --reports to read; default: removed")
    args = bench.parse_args(ap, argv)
    bench.note(f"{args.loads} CPU-bound load(s) on {os.cpu_count()} cores; limit {args.limit_s:.0f} s; "
               "fresh clone, .venv and cache each repetition; the clone is of the last commit, so what is "
               "uncommitted in this checkout (the record's dirty flag) is not measured")
    bench.figure("wall_s", "make search wall time, setup included", "s", "lower")
    bench.figure("over_limit", "wall time / limit (target 1.10 or less)", "x", "lower")
    bench.figure("winner_over_best_baseline", "retrained winner / best retrained baseline", "x", "lower")
    bench.figure("winner_over_paper", "retrained winner / retrained paper design (the study's summary)", "x", "lower")
    bench.figure("summary_honest", "summary names a baseline the best model when no candidate beat it (1 = yes)",
                 "", "higher")
    for rep in bench.repetitions():
        loaded_run(bench, args.loads, args.limit_s, rep, args.keep)
    bench.finish()


# -- test_suite -------------------------------------------------------------------------------

RUNS = {"default": [], "one_process": ["TEST_WORKERS=0"]}


PASSED = re.compile(r"(\d+) passed")


def make_test(variables: list[str]) -> tuple[float, int]:
    """``make test`` with ``variables``: (its wall seconds, the tests passed)."""
    started = time.perf_counter()
    done = subprocess.run(["make", "-s", "test", *variables], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    seconds = time.perf_counter() - started
    tail = (done.stdout + done.stderr).strip().splitlines()[-1:] or [""]
    if done.returncode != 0:
        raise SystemExit(f"make test {' '.join(variables)} failed (exit {done.returncode}): {tail[0]}")
    passed = PASSED.search(tail[0])
    print(f"  make test {' '.join(variables) or '(default workers)'}: {seconds:.0f} s, {tail[0]}", flush=True)
    return seconds, int(passed.group(1)) if passed else 0


def bench_test_suite(argv: Sequence[str] | None = None) -> None:
    """How long ``make test`` takes with its default workers (pytest-xdist, one process per core, at most
    4) against ``TEST_WORKERS=0`` (every test in one process), on this machine: the README's command
    itself, run from the repository root, the two interleaved (their order rotating from repetition to
    repetition). Figures: each one's wall time, the ratio of the two in the same repetition, and the tests
    each passed (a run that fails stops the benchmark: a faster failure is no figure).

        python -m benchmarks.commands --only test_suite [--reps 3]

    Nothing else should run beside it: both runs use every core.
    """
    bench = Bench("bench_test_suite", "make test: one process per core against one process",
                  bench_test_suite.__doc__)
    bench.parse_args(bench.parser(), argv)
    for name in RUNS:
        bench.figure(f"wall_s_{name}", f"make test, {name.replace('_', ' ')}: wall time", "s", better="lower")
        bench.figure(f"passed_{name}", f"make test, {name.replace('_', ' ')}: tests passed", "")
    bench.figure("speedup", "one process's wall time / the default's, same repetition", "x", better="higher")
    bench.note(f"{os.cpu_count()} cores; make test's default workers min(cores, 4); "
               f"the suite as of this commit, the shared data {'present' if (ROOT.parent / 'shared' / 'data').is_dir() else 'absent'}")
    for rep in bench.repetitions():
        wall = {}
        for name in rotated(list(RUNS), rep):
            wall[name], passed = make_test(RUNS[name])
            bench.add(f"wall_s_{name}", wall[name])
            bench.add(f"passed_{name}", passed)
        bench.add("speedup", wall["one_process"] / wall["default"])
    bench.finish()


# -- finalists --------------------------------------------------------------------------------

def _estimates(config: SearchConfig, count: int, seed: int = 0) -> list[optuna.trial.FrozenTrial]:
    """``count`` random candidates of the space with made-up estimates (what retraining starts from)."""
    space, rng = SearchSpace.from_yaml(config.space), random.Random(seed)
    sampler = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed))
    out = []
    for _ in range(count):
        cand = space.sample(sampler.ask())
        out.append(optuna.trial.create_trial(values=[rng.uniform(0.3, 0.6)], user_attrs={
            "candidate": cand.to_dict(), "candidate_key": cand.key, "path_metrics": [], "workloads": {}}))
    return out


def _retrain(config: SearchConfig, estimates, workers: int) -> float:
    study = optuna.create_study(study_name=config.study, storage=optuna.storages.InMemoryStorage())
    for t in estimates:
        study.add_trial(t)
    with tempfile.TemporaryDirectory() as reports:
        start = time.perf_counter()
        retrain_finalists(study, config.resolve(), Path(reports), workers=workers)
        seconds = time.perf_counter() - start
    expected = config.finalists + len(config.baselines)
    if len(finalist_trials(study)) != expected:
        raise SystemExit(f"{len(finalist_trials(study))} retrained, not {expected}")
    return seconds


def bench_finalists(argv: Sequence[str] | None = None) -> None:
    """Finalists retrained one after another against ``--workers N`` processes at once: the wall time of
    retraining the same jobs (K finalists of the default space and the paper design, the finalists'
    recipe at a reduced step count) both ways, and the ratio. On a CPU the workers share the cores, so
    the gain is what running whole trainings side by side adds over PyTorch's threads inside one; on a
    machine with several GPUs every worker has a GPU of its own (run it there with ``--accelerator cuda``).

        python -m benchmarks.commands --only finalists [--reps 3] [--finalists 2] [--steps 60] [--workers 2]
        python -m benchmarks.commands --only finalists --accelerator cuda --size 224x224 --batch-size 64   # a GPU's study

    Each repetition retrains the jobs sequentially and in parallel, in an order that rotates, in fresh
    folders (nothing resumes); the estimates they are chosen from are the same every time.
    """
    bench = Bench("bench_finalists", "Finalists retrained sequentially and by worker processes at once",
                  bench_finalists.__doc__)
    ap = bench.parser()
    ap.add_argument("--finalists", type=int, default=2, help="finalists retrained (the paper design beside them)")
    ap.add_argument("--steps", type=int, default=60, help="training steps of each retraining")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the parallel run")
    ap.add_argument("--accelerator", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--size", type=image_size, help="train and deploy at this size, HxW (default: the search's "
                    "defaults, 64x64 then tuned at 224x224); 224x224 with --batch-size 64 is a GPU's study")
    ap.add_argument("--batch-size", type=int, default=16, help="frames a step (default 16)")
    args = bench.parse_args(ap, argv)
    sizes = {"train_size": args.size, "input_size": args.size} if args.size else {}
    config = SearchConfig(study="bench-finalists", finalists=args.finalists, finalist_steps=args.steps,
                          baselines=("paper",), accelerator=args.accelerator, keep_weights=False,
                          batch_size=args.batch_size, **sizes)
    estimates = _estimates(config, 12)
    open_dataset(config.data, "train", config.train_size, seed=config.seed)   # generated once, before timing
    open_dataset(config.data, "val", config.train_size, train_augment=False)
    bench.figure("sequential_s", f"{args.finalists} finalists + paper design, one after another", "s", "lower")
    bench.figure("parallel_s", f"the same, {args.workers} workers at once", "s", "lower")
    bench.figure("speedup", "sequential / parallel", "x", "higher")
    for rep in bench.repetitions():
        took = {}
        for mode in rotated(["sequential", "parallel"], rep):
            took[mode] = _retrain(dataclasses.replace(config, study=f"bench-{mode}"), estimates,
                                  1 if mode == "sequential" else args.workers)
        bench.add("sequential_s", took["sequential"])
        bench.add("parallel_s", took["parallel"])
        bench.add("speedup", took["sequential"] / took["parallel"])
    bench.finish()


CASES = (Case(bench_search_memory, cpu=False, skip="runs make search's job, about 16 minutes a repetition"),
         Case(bench_make_search_load, cpu=False, skip="runs make search from a fresh clone beside a load, repeatedly"),
         Case(bench_test_suite, cpu=False, skip="runs make test twice a repetition, with nothing beside it"),
         Case(bench_finalists))

if __name__ == "__main__":
    run_suite(CASES)
