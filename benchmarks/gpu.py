"""Training and searching on a GPU (and the search's rate on a CPU).

    python -m benchmarks.gpu --list
    python -m benchmarks.gpu --only NAME [its options]
"""

from __future__ import annotations

import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Sequence

from explorer.deploy.manifest import Manifest, read_manifest
from explorer.study import trial_record

from benchmarks.harness import Bench, Case, RESULTS, ROOT, image_size, interleave, python_path, run_suite


# -- gpu --------------------------------------------------------------------------------------

DEFAULT, LARGE = ((64, 64), 16), ((224, 224), 64)


class Utilisation:
    """Samples a GPU's utilisation (%) in a thread while ``active``; ``source`` is "pynvml", "nvidia-smi"
    or None (no way to read it here)."""

    def __init__(self, index: int | None) -> None:
        self.index, self.samples, self.times, self.active = index, [], [], False   # values (%), when read
        self.source, self._read = (None, None) if index is None else self._reader(index)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True) if self._read else None

    @staticmethod
    def _reader(index: int):
        index = physical_index(index)
        try:
            import pynvml
            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(index)
            return "pynvml", lambda: float(pynvml.nvmlDeviceGetUtilizationRates(handle).gpu)
        except Exception:   # not installed, or no driver: try the command line tool
            pass
        cmd = ["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits", "-i", str(index)]
        try:
            float(subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=True).stdout.strip())
        except Exception:
            return None, None
        return "nvidia-smi", lambda: float(subprocess.run(cmd, capture_output=True, text=True, timeout=10).stdout.strip())

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            if self.active:
                try:
                    value = self._read()
                    self.samples.append(value)
                    self.times.append(time.time())
                except Exception:   # a sample that failed is a sample fewer, not a failed benchmark
                    pass

    def __enter__(self):
        if self._thread:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join()

    def take(self) -> float | None:
        """The mean of the samples since the last take, or None."""
        got, self.samples, self.times = self.samples, [], []
        return statistics.fmean(got) if got else None


def physical_index(index: int) -> int:
    """The driver's index (what NVML and nvidia-smi count) of PyTorch's GPU ``index``, which counts only
    the devices CUDA_VISIBLE_DEVICES lists."""
    visible = [v.strip() for v in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
    return int(visible[index]) if index < len(visible) and visible[index].isdigit() else index


def train_steps(device: str, size: tuple[int, int], batch: int, steps: int, data: str, amp: bool,
                util: Utilisation | None = None, out: Path | None = None, warm: int = 2,
                graphs: bool = True, micro_batches: int = 1) -> float:
    """Median seconds per step of the last ``steps`` of ``warm + steps`` supernet steps on ``device``
    (NaN in a torchrun process other than the first, whose progress is not reported). Every width
    trains from the first step (no progressive shrinking), so that the untimed ``warm`` steps meet most
    of the stage configurations a run has: their CUDA graphs (``graphs``) are captured and cuDNN's plans
    made before the timing, as in a long run's steady state."""
    import torch
    from explorer.space import SearchSpace
    from explorer.supernet import SupernetRecipe, train_supernet
    recipe = SupernetRecipe(steps=warm + steps, batch_size=batch, input_size=size, amp=amp, shrink=0.0,
                            cuda_graphs=graphs, micro_batches=micro_batches)
    times: list[float] = []

    def progress(step, total, record):
        if step > warm:
            times.append(record["step_seconds"])
        if util is not None:
            util.active = step >= warm and step < total
    with tempfile.TemporaryDirectory() as tmp:
        train_supernet(SearchSpace.from_yaml("anytime_depth"), data, recipe, out or Path(tmp) / "s.pt",
                       torch.device(device), progress=progress, checkpoint_every=10**9)
    if util is not None:
        util.active = False
    return statistics.median(times) if times else float("nan")   # under torchrun, rank 0 alone is told


def worker(args) -> None:
    """One process of the torchrun comparison: trains, and rank 0 writes its median step time."""
    seconds = train_steps(args.device, args.size, args.batch, args.steps, args.data, amp=False, warm=args.warmup_steps)
    if int(os.environ.get("RANK", "0")) == 0:
        Path(args.worker).write_text(json.dumps({"step_s": seconds}))


def processes_step(device: str, nproc: int, steps: int, data: str, warm: int) -> float:
    """Median step time of ``nproc`` processes sharing ``device`` at the default recipe (torchrun for 2+)."""
    (size, batch) = DEFAULT
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "times.json"
        script = ["-m", "benchmarks.gpu", "--only", "gpu", "--worker", str(out), "--device", device,
                  "--steps", str(steps), "--warmup-steps", str(warm), "--data", data,
                  "--size", f"{size[0]}x{size[1]}", "--batch", str(batch)]
        launch = [sys.executable] + (["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc)]
                                     if nproc > 1 else [])
        env = {**os.environ, "PYTHONPATH": python_path()}
        if device == "cpu":
            env["OMP_NUM_THREADS"] = str(max(1, cores() // nproc))
        run = subprocess.run(launch + script, cwd=ROOT, env=env, capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"{nproc} process(es) failed: {run.stderr[-2000:]}")
        return json.loads(out.read_text())["step_s"]


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def search_config(study: str, device: str, data: str, supernet_steps: int):
    from explorer.study.search import SearchConfig
    return SearchConfig(study=study, data=data, evaluator="supernet", supernet_steps=supernet_steps, finalists=0,
                        keep_weights=False, accelerator=device)


def search_rate(device: str, data: str, seconds: float, supernet_steps: int) -> tuple[float, float]:
    """(distinct candidates evaluated per minute, share of the sampling time in the evaluator) of a
    supernet search sampling ``seconds`` (its supernet trained beforehand, outside the time)."""
    import optuna
    from explorer.study.search import SearchRun, search
    optuna.logging.set_verbosity(optuna.logging.WARNING)   # a line per trial would bury the figures
    config = search_config(f"gpu-bench-{random.randrange(10**9)}", device, data, supernet_steps)
    with tempfile.TemporaryDirectory() as tmp:
        out = search(config.resolve(), SearchRun(n_trials=None, timeout_s=seconds, reports=Path(tmp)))
        trials = [t for t in out.study.get_trials() if t.state.name == "COMPLETE"]
        if not trials:   # a machine too busy to finish one in the time: the study goes on until one is done
            out = search(config.resolve(), SearchRun(n_trials=1, timeout_s=None, reports=Path(tmp)))
            trials = [t for t in out.study.get_trials() if t.state.name == "COMPLETE"]
    if not trials:
        raise RuntimeError("the search finished no trial")
    wall = (max(t.datetime_complete for t in trials) - min(t.datetime_start for t in trials)).total_seconds()
    evaluated = [t for t in trials if trial_record(t).duplicate_of is None and trial_record(t).evaluator]
    distinct = len({trial_record(t).candidate_key for t in trials})
    in_evaluator = sum(float(trial_record(t).evaluator.get("seconds", 0.0)) for t in evaluated)
    return distinct / wall * 60.0, in_evaluator / wall


def subnet_losses(files: list[Path], device: str, data: str, size: tuple[int, int]) -> list[list[float]]:
    """Each supernet file's validation L1 (all exits) on the same 10 subnets of the default space (the
    largest, the smallest, 8 random) and the same 32 frames, in float32 with batch statistics."""
    import torch
    from explorer.data import open_dataset
    from explorer.space import SearchSpace
    from explorer.supernet import load_supernet, largest_candidate, random_training_subnet, smallest_candidate
    from explorer.training.train import multi_exit_loss
    space = SearchSpace.from_yaml("anytime_depth")
    rng = random.Random(7)
    subnets = [largest_candidate(space), smallest_candidate(space)] + [random_training_subnet(space, rng)
                                                                       for _ in range(8)]
    val = open_dataset(data, "val", size, train_augment=False)
    frames = [val[i] for i in range(min(len(val), 32))]
    image, scan, depth = (torch.stack([f[k] for f in frames]).to(device) for k in ("image", "scan", "depth"))
    out = []
    for file in files:
        net = load_supernet(file, space)[0].to(device).train()
        with torch.no_grad():
            out.append([float(multi_exit_loss(net.forward_subnet(c, image, scan, frames[0]["scan_row"]), depth)[0])
                        for c in subnets])
    return out


def amp_effect(device: str, data: str, steps: int, size: tuple[int, int], batch: int) -> tuple[float, float]:
    """(bf16 / float32 validation L1 over the same subnets, Kendall tau of the two supernets' rankings of
    them) after ``steps`` steps each (:func:`subnet_losses`)."""
    from scipy.stats import kendalltau
    with tempfile.TemporaryDirectory() as tmp:
        files = [Path(tmp) / f"amp{amp}.pt" for amp in (False, True)]
        for amp, out in zip((False, True), files):
            train_steps(device, size, batch, steps, data, amp, out=out, warm=0)   # trained, not timed
        plain, bf16 = subnet_losses(files, device, data, size)
    tau = kendalltau(plain, bf16).statistic
    return statistics.fmean(bf16) / statistics.fmean(plain), float(tau)


def options(bench: Bench):
    ap = bench.parser()
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"],
                    help="where to train and search (default: CUDA where PyTorch sees a GPU, else the CPU)")
    ap.add_argument("--steps", type=int, default=20, help="timed supernet steps per timing (default 20)")
    ap.add_argument("--large-size", type=image_size, default=LARGE[0], help="the large recipe's size HxW (default 224x224)")
    ap.add_argument("--large-batch", type=int, default=LARGE[1], help="the large recipe's batch (default 64)")
    ap.add_argument("--large-steps", type=int, default=None, help="steps at the large recipe (default --steps)")
    ap.add_argument("--warmup-steps", type=int, default=60, help="untimed steps before each timing on the GPU, "
                    "in the same run (its stage graphs captured, cuDNN's plans made; default 60); the CPU's "
                    "timings take 3, the torchrun comparison's at most 10")
    ap.add_argument("--search-seconds", type=float, default=8.0, help="sampling time of each search (default 8)")
    ap.add_argument("--search-supernet-steps", type=int, default=30,
                    help="steps of the search's supernet, trained once before the repetitions (default 30)")
    ap.add_argument("--amp-steps", type=int, default=60, help="steps of each supernet of the bf16 comparison, "
                    "at the default recipe (default 60; 0 skips it)")
    ap.add_argument("--data", default="synthetic:400:100",
                    help="data set of every training and search (default synthetic:400:100)")
    ap.add_argument("--cpu-threads", type=int, default=2, help="threads of the CPU step the GPU's is compared "
                    "with (default 2: the 2-core machine the targets name)")
    ap.add_argument("--no-torchrun", action="store_true", help="skip the two-process comparison")
    # one process of the torchrun comparison (internal)
    ap.add_argument("--worker", help=argparse_hidden())
    ap.add_argument("--size", type=image_size, default=DEFAULT[0], help=argparse_hidden())
    ap.add_argument("--batch", type=int, default=DEFAULT[1], help=argparse_hidden())
    return ap


def argparse_hidden():
    import argparse
    return argparse.SUPPRESS


def declare(bench: Bench, on_gpu: bool) -> None:
    where = "GPU" if on_gpu else "CPU"
    bench.figure("step_s_default", f"{where} supernet step, 64x64 batch 16", "s", better="lower")
    bench.figure("step_s_large", f"{where} supernet step, large recipe (bf16 on CUDA)", "s", better="lower")
    bench.figure("step_s_one_process", f"{where} step, one process (torchrun comparison)", "s", better="lower")
    bench.figure("step_s_two_processes", f"{where} step, two processes sharing it", "s", better="lower")
    bench.figure("two_process_speedup", "one process / two processes, step time", "x", better="higher")
    bench.figure("candidates_per_minute", "distinct candidates per minute, supernet search", "1/min",
                 better="higher")
    bench.figure("evaluator_share", "share of sampling time in the evaluator", "", better="higher")
    bench.figure("amp_loss_ratio", "bf16 / float32 supernet validation L1", "x", better="lower")
    bench.figure("amp_rank_tau", "Kendall tau, bf16 vs float32 supernet rankings", "", better="higher")
    if on_gpu:
        bench.figure("gpu_util_default", "GPU utilisation, default recipe", "%", better="higher")
        bench.figure("step_s_default_no_graphs", "GPU supernet step, 64x64 batch 16, no CUDA graphs", "s",
                     better="lower")
        bench.figure("graphs_speedup_default", "step time without / with CUDA graphs, default recipe", "x",
                     better="higher")
        bench.figure("gpu_util_default_no_graphs", "GPU utilisation, default recipe, no CUDA graphs", "%",
                     better="higher")
        bench.figure("gpu_util_large", "GPU utilisation, large recipe", "%", better="higher")
        bench.figure("cpu_step_s_default", "CPU supernet step on --cpu-threads threads, 64x64 batch 16", "s",
                     better="lower")
        bench.figure("gpu_speedup_default", "CPU / GPU step time, default recipe", "x", better="higher")


def one_repetition(bench: Bench, args, device: str, util: Utilisation | None, rep: int) -> None:
    on_gpu = device == "cuda"
    size, batch = DEFAULT
    warm = args.warmup_steps if on_gpu else 3

    def default(graphs: bool) -> float:
        seconds = train_steps(device, size, batch, args.steps, args.data, False, util, warm=warm, graphs=graphs)
        _add_util(bench, "gpu_util_default" if graphs else "gpu_util_default_no_graphs", util)
        return seconds
    if on_gpu:   # with and without CUDA graphs, in turn (a CPU has no graphs)
        got = interleave({g: (lambda g=g: default(g)) for g in (True, False)}, rep)
        bench.add("step_s_default", got[True])
        bench.add("step_s_default_no_graphs", got[False])
        bench.add("graphs_speedup_default", got[False] / got[True])
    else:
        bench.add("step_s_default", default(False))
    bench.add("step_s_large", train_steps(device, args.large_size, args.large_batch, args.large_steps or args.steps,
                                          args.data, on_gpu, util, warm=warm))
    _add_util(bench, "gpu_util_large", util)
    if on_gpu:
        import torch
        threads = torch.get_num_threads()
        torch.set_num_threads(args.cpu_threads)
        try:
            cpu = bench.add("cpu_step_s_default", train_steps("cpu", size, batch, args.steps, args.data, False, warm=3))
        finally:
            torch.set_num_threads(threads)
        bench.add("gpu_speedup_default", cpu / bench.figures["step_s_default"].reps[-1])
    if not args.no_torchrun:   # in an order that turns over from one repetition to the next
        got = interleave({n: (lambda n=n: processes_step(device, n, args.steps, args.data, min(warm, 10)))
                          for n in (1, 2)}, rep)
        bench.add("step_s_one_process", got[1])
        bench.add("step_s_two_processes", got[2])
        bench.add("two_process_speedup", got[1] / got[2])
    per_minute, share = search_rate(device, args.data, args.search_seconds, args.search_supernet_steps)
    bench.add("candidates_per_minute", per_minute)
    bench.add("evaluator_share", share)


def warm_up(args, device: str) -> None:
    """The recipes' and the search's first steps, untimed: the timings are then a long run's steady state.
    cuDNN builds a plan for each convolution shape it has not seen, and a random subnet's shapes are
    mostly new in a run's first steps (on an H100 those steps took several times a later one)."""
    started = time.perf_counter()
    train_steps(device, DEFAULT[0], DEFAULT[1], 3, args.data, False)
    train_steps(device, args.large_size, args.large_batch, 3, args.data, device == "cuda")
    search_rate(device, args.data, args.search_seconds, args.search_supernet_steps)
    print(f"warm-up: a few steps a recipe and a search, {time.perf_counter() - started:.0f} s",
          flush=True)


def _add_util(bench: Bench, name: str, util: Utilisation | None) -> None:
    value = util.take() if util is not None else None
    if value is None:
        if util is not None:
            print(f"  {bench.figures[name].label}: n/a (no pynvml, no nvidia-smi)", flush=True)
        return
    bench.add(name, value)


def bench_gpu(argv: Sequence[str] | None = None) -> None:
    """One GPU (or, for the ratio, the CPU) put to work by the project's own training and search: supernet
    training's time per step and the GPU's utilisation at the default recipe (64x64, batches of 16) and at
    the GPU recipe's size (224x224, batches of 64, bf16 autocast); two processes sharing the device under
    torchrun against one; a short supernet search's distinct candidates per minute and the share of its
    sampling time spent in the evaluator; and what bf16 autocast does to the supernet's validation loss.

        python -m benchmarks.gpu --only gpu                      # the GPU where PyTorch sees one, else the CPU
        python -m benchmarks.gpu --only gpu --device cpu         # the same figures on the CPU (printed, not recorded)
        python -m benchmarks.gpu --only gpu --steps 4 --large-size 64x64 --large-batch 8 --search-seconds 10 \
            --amp-steps 2 --data synthetic:64:32 --reps 1 --no-record      # a smoke run

    Step times are the median over a timed run's last --steps steps, after --warmup-steps untimed ones in
    the same run (on a CPU, 3): by then the run's CUDA graphs of its stages are captured and cuDNN has
    its plans, a long run's steady state. Every width trains from the first step (no progressive
    shrinking) so that the untimed steps meet most stage configurations. Step times are read after each
    step's losses reach the host (a GPU's queue is drained every step). On a GPU the default recipe is
    timed with and without CUDA graphs, in turn. Utilisation is sampled with pynvml where it imports,
    else nvidia-smi, every 0.1-0.2 s over the timed steps ("n/a" without either). On a CUDA device the
    CPU's step time at the default recipe (on --cpu-threads threads) is measured in the same run, for the
    speed-up. The search trains its small supernet once (not timed), then samples for --search-seconds
    per repetition; its sampling time runs from the first trial's start to the last one's end. Before
    the repetitions, a few steps at each recipe and an untimed search start the process's CUDA context
    and libraries. bf16 is measured once per run: two supernets trained alike, one under autocast,
    evaluated in float32 on the same validation frames and subnets.
    """
    bench = Bench("bench_gpu", "one GPU kept busy: supernet steps, utilisation, torchrun, search throughput, bf16",
                  bench_gpu.__doc__)
    args = bench.parse_args(options(bench), argv)
    if args.worker:
        return worker(args)
    import torch
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench_gpu: --device cuda, but PyTorch sees no GPU (use --device cpu)")
    on_gpu = device == "cuda"
    if not on_gpu and args.results == RESULTS and not args.no_record:
        # the project's records of this benchmark are a GPU's (the docs quote the latest as one); a CPU's
        # search rate has its own benchmark, bench_search_rate
        print("bench_gpu: no GPU, so no record in benchmarks/results (give --results DIR to keep one)", flush=True)
        args.no_record = True
    declare(bench, on_gpu)
    from explorer.study.search import ensure_supernet
    ensure_supernet(search_config("gpu-bench", device, args.data, args.search_supernet_steps).resolve())   # not timed
    with Utilisation(torch.cuda.current_device() if on_gpu else None) as util:
        if on_gpu:
            bench.note(f"{torch.cuda.get_device_name()}; utilisation read with {util.source or 'nothing (n/a)'}")
        bench.note(f"data {args.data}; large recipe {args.large_size[0]}x{args.large_size[1]}, batch "
                   f"{args.large_batch}{', bf16 autocast' if on_gpu else ', float32'}; {args.steps} steps a timing; "
                   f"searches sample {args.search_seconds:g} s on a {args.search_supernet_steps}-step supernet")
        if args.warmup_steps:
            warm_up(args, device)
        for rep in bench.repetitions():
            one_repetition(bench, args, device, util if on_gpu else None, rep)
    if args.amp_steps:
        ratio, tau = amp_effect(device, args.data, args.amp_steps, *DEFAULT)
        bench.add("amp_loss_ratio", ratio)
        bench.add("amp_rank_tau", tau)
        bench.note(f"bf16: two supernets of {args.amp_steps} steps at 64x64, batch 16, 10 subnets compared")
    bench.finish()


# -- gpu_study --------------------------------------------------------------------------------

PHASES = ("data", "measuring", "supernet", "sampling", "finalists", "report", "export")


def _explorer(*args: str, must: bool = True) -> float | None:
    """Runs ``explorer ARGS`` as a user would (a fresh process); its wall seconds. A failure ends the
    benchmark with the command's last output, or, where not a ``must``, is printed and gives None."""
    started = time.time()
    proc = subprocess.run([sys.executable, "-m", "explorer", *args], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": python_path()})
    print(proc.stdout[-2500:], flush=True)
    if proc.returncode != 0:
        message = f"explorer {args[0]} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
        if must:
            raise SystemExit(message)
        print(message, flush=True)
        return None
    return time.time() - started


def phase_spans(run: dict, search_end: float, export_s: float) -> dict[str, tuple[float, float]]:
    """(start, end) wall-clock seconds of each phase: the study's own phases from its run record, then
    the report (the rest of the search command) and the export."""
    start = time.mktime(time.strptime(run["started"], "%Y-%m-%d %H:%M:%S"))
    spans, t = {}, start
    for name, seconds in run["phases"].items():
        spans[name] = (t, t + seconds)
        t += seconds
    spans["report"] = (start + run["seconds"], search_end)
    spans["export"] = (search_end, search_end + export_s)
    return spans


def export_gap(manifest: Manifest) -> float:
    """The largest |error as exported - error as the study reported| over the winner's paths (RMSE, m)."""
    study = manifest.source.study_path_metrics
    return max(abs(a["rmse"] - b["rmse"]) for a, b in zip(manifest.path_metrics, study))


def one_study(bench: Bench, args, rep: int, util: Utilisation) -> None:
    import optuna
    from explorer.study import study_record
    from explorer.study.results import baseline_trial, is_retrained, winner
    from explorer.study.storage import load_study
    size = f"{args.size[0]}x{args.size[1]}"
    with tempfile.TemporaryDirectory() as tmp:
        reports, name = Path(tmp) / "reports", f"gpu-study-{rep}"
        util.samples, util.times, util.active = [], [], True
        _explorer("search", "--device", args.device, "--accelerator", args.accelerator, "--data", args.data,
                  "--train-size", size, "--input-size", size, "--batch-size", str(args.batch_size),
                  *(["--amp"] if args.amp else []), "--time-limit", args.time_limit, "--study", name,
                  *(["--finalists", str(args.finalists)] if args.finalists is not None else []),
                  *(["--finalist-steps", str(args.finalist_steps)] if args.finalist_steps is not None else []),
                  "--seed", str(rep), "--reports", str(reports))
        search_end = time.time()
        export_s = _explorer("export", "--study", name, "--reports", str(reports), "--out", str(Path(tmp) / "winner"),
                             must=False)
        util.active = False
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        study = load_study(name, reports=reports)
        stored = study_record(study)
        run, trials = stored.runs[-1], len(study.trials)
        plan = stored.plan.model_dump() if stored.plan is not None else {}
        best, paper = winner(study), baseline_trial(study, "paper", retrained=True)
        exported = Path(tmp) / "winner" / "manifest.json"
        manifest = read_manifest(exported.parent) if export_s is not None else None
        if args.keep:   # the study's report and the export's manifest, to read
            args.keep.mkdir(parents=True, exist_ok=True)
            shutil.copy(reports / name / "report.html", args.keep / f"report-{rep}.html")
            if manifest is not None:
                shutil.copy(exported, args.keep / f"manifest-{rep}.json")
    bench.add("study_s", run["seconds"])
    for phase, (t0, t1) in phase_spans(run, search_end, export_s or 0.0).items():
        if phase == "export" and export_s is None:
            continue
        bench.add(bench.figure(f"{phase}_s", f"{phase}, wall time", "s", "lower"), t1 - t0)
        if util.source is not None:
            inside = [v for t, v in zip(util.times, util.samples) if t0 <= t < t1]
            if inside:
                bench.add(bench.figure(f"gpu_util_{phase}", f"GPU utilisation, {phase}", "%"),
                          sum(inside) / len(inside))
    if manifest is not None:
        bench.add("export_rmse_gap", export_gap(manifest))
    bench.note(f"study {rep}: supernet {plan.get('supernet_steps')} steps, {trials} trials, "
               f"{plan.get('finalists')} finalist(s) of {plan.get('finalist_steps')} steps, winner trial "
               f"{best.number if best is not None else None}")
    if best is None or not is_retrained(best) or paper is None:   # the time limit left no retraining
        bench.note(f"study {rep} retrained no finalist or no paper design: no ratio (a longer --time-limit)")
        return
    bench.add("winner_ratio", best.values[0] / paper.values[0])


def bench_gpu_study(argv: Sequence[str] | None = None) -> None:
    """A whole study at the size it deploys, run as a user runs it on one GPU: ``explorer search`` with the
    supernet, the sampling, the finalists and the baselines all at 224x224 (bf16 autocast, batches of 64)
    under ``--time-limit``, its HTML report, then ``explorer export`` of the winner. Figures: each phase's
    wall time as the study records it, the GPU's mean utilisation in each phase, the winner's anytime loss
    over the retrained paper design's (both measured at 224x224), and the largest gap between a path's
    error as the export measured it (onnxruntime, the exported graphs) and as the study reported it.

        python -m benchmarks.gpu --only gpu_study --reps 1                 # a 4-minute study on the GPU PyTorch sees
        python -m benchmarks.gpu --only gpu_study --reps 1 --accelerator cpu --size 32x32 --batch-size 8 \
            --no-amp --data synthetic:32:16 --time-limit 2m --finalists 1 --finalist-steps 20 --no-record   # a CPU

    A study takes minutes, so a run of this benchmark is usually one repetition (give ``--reps 1``): its
    figures are one study's, and the record says so. Each repetition is a new study (seed = repetition)
    in a fresh folder; the data set is generated once, into the cache, before the first (not timed).
    Utilisation is sampled every 0.1-0.2 s (pynvml, else nvidia-smi; "n/a" without either) and assigned to
    a phase by the phase times the study recorded, whose start is read to the second.
    """
    bench = Bench("bench_gpu_study", "a whole study at the deployment size on one GPU: phases, utilisation, winner",
                  bench_gpu_study.__doc__)
    ap = bench.parser()
    ap.add_argument("--time-limit", default="4m", help="the study's --time-limit (default 4m)")
    ap.add_argument("--size", type=image_size, default=(224, 224), help="training and deployment size (default 224x224)")
    ap.add_argument("--batch-size", type=int, default=64, help="frames a step (default 64)")
    ap.add_argument("--no-amp", dest="amp", action="store_false", help="float32 instead of bf16 autocast")
    ap.add_argument("--accelerator", default="cuda", choices=("cuda", "cpu"), help="where to train (default cuda)")
    ap.add_argument("--device", default="tx2", help="the study's device profile (default tx2)")
    ap.add_argument("--data", default="synthetic", help="the study's data (default synthetic)")
    ap.add_argument("--keep", type=Path, help="copy each study's report.html and the export's manifest.json here")
    ap.add_argument("--finalists", type=int, help="the study's --finalists (default: what the plan fits)")
    ap.add_argument("--finalist-steps", type=int, help="the study's --finalist-steps (default: the plan's)")
    args = bench.parse_args(ap, argv)
    import torch
    on_gpu = args.accelerator == "cuda"
    if on_gpu and not torch.cuda.is_available():
        raise SystemExit("bench_gpu_study: PyTorch sees no GPU (--accelerator cpu for a smoke run)")
    from explorer.data import open_dataset
    open_dataset(args.data, "train", args.size)   # generated once, before the timing
    bench.figure("study_s", "the search command's run (data to finalists)", "s", "lower")
    bench.figure("winner_ratio", "winner / paper design, anytime loss, both retrained at the size", "x", "lower")
    bench.figure("export_rmse_gap", "largest |exported path RMSE - study's|", "m", "lower")
    with Utilisation(torch.cuda.current_device() if on_gpu else None) as util:
        bench.note(f"{torch.cuda.get_device_name() if on_gpu else 'CPU'}; {args.size[0]}x{args.size[1]}, batch "
                   f"{args.batch_size}{', bf16 autocast' if args.amp else ''}; --time-limit {args.time_limit}; data "
                   f"{args.data}; utilisation read with {util.source or 'nothing (n/a)'}")
        for rep in bench.repetitions():
            one_study(bench, args, rep, util)
    bench.finish()


# -- search_rate ------------------------------------------------------------------------------

def bench_search_rate(argv: Sequence[str] | None = None) -> None:
    """A supernet search as ``explorer search --device tx2`` runs it on this machine: distinct candidates
    evaluated per minute, and the share of the sampling time spent in the evaluator (the rest is the
    sampler, costing and the study's storage). The default data and the default supernet (600 steps,
    cached; trained first, untimed, where it is missing), on the device a search picks (CUDA where PyTorch
    sees a GPU, else the CPU).

        python -m benchmarks.gpu --only search_rate [--reps 3] [--seconds 60] [--device cpu|cuda]

    Each repetition samples ``--seconds`` on a fresh study; an untimed search first builds what a long
    search has built by then (the costing's stage cache, cuDNN's plans on a GPU). Sampling time runs from
    the first trial's start to the last one's end.
    """
    bench = Bench("bench_search_rate", "a supernet search's throughput: distinct candidates per minute, evaluator share",
                  bench_search_rate.__doc__)
    ap = bench.parser()
    ap.add_argument("--seconds", type=float, default=60.0, help="sampling time per repetition (default 60)")
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"],
                    help="where the evaluator runs (default: CUDA where PyTorch sees a GPU, else the CPU)")
    ap.add_argument("--data", default="synthetic", help="data set (default: the search's, synthetic)")
    ap.add_argument("--supernet-steps", type=int, default=600, help="the supernet's steps (default 600, "
                    "the search's)")
    args = bench.parse_args(ap, argv)
    import torch
    from explorer.study.search import ensure_supernet
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    ensure_supernet(search_config("search-rate", device, args.data, args.supernet_steps).resolve())   # not timed
    rate = bench.figure("candidates_per_minute", "distinct candidates per minute", "1/min", "higher")
    per_ten = bench.figure("candidates_per_10_min", "distinct candidates per 10 minutes", "", "higher")
    share = bench.figure("evaluator_share", "share of sampling time in the evaluator", "", "higher")
    bench.note(f"{device}, {torch.get_num_threads()} threads; data {args.data}; {args.supernet_steps}-step "
               f"supernet; {args.seconds:g} s of sampling a repetition, after an untimed one")
    search_rate(device, args.data, args.seconds, args.supernet_steps)   # warm-up, untimed
    for _ in bench.repetitions():
        per_minute, in_evaluator = search_rate(device, args.data, args.seconds, args.supernet_steps)
        bench.add(rate, per_minute)
        bench.add(per_ten, per_minute * 10)
        bench.add(share, in_evaluator)
    bench.finish()


CASES = (Case(bench_gpu, cpu=False, skip="its figures are a GPU's"),
         Case(bench_gpu_study, cpu=False, skip="a whole study a repetition on a GPU"),
         Case(bench_search_rate, cpu=False, skip="trains the default supernet before sampling (long on a CPU)"))

if __name__ == "__main__":
    run_suite(CASES)
