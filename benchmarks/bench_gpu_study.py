"""A whole study at the size it deploys, run as a user runs it on one GPU: ``explorer search`` with the
supernet, the sampling, the finalists and the baselines all at 224x224 (bf16 autocast, batches of 64)
under ``--time-limit``, its HTML report, then ``explorer export`` of the winner. Figures: each phase's
wall time as the study records it, the GPU's mean utilisation in each phase, the winner's anytime loss
over the retrained paper design's (both measured at 224x224), and the largest gap between a path's
error as the export measured it (onnxruntime, the exported graphs) and as the study reported it.

    python benchmarks/bench_gpu_study.py --reps 1                 # a 4-minute study on the GPU PyTorch sees
    python benchmarks/bench_gpu_study.py --reps 1 --accelerator cpu --size 32x32 --batch-size 8 \\
        --no-amp --data synthetic:32:16 --time-limit 2m --finalists 1 --finalist-steps 20 --no-record   # a CPU

A study takes minutes, so a run of this benchmark is usually one repetition (give ``--reps 1``): its
figures are one study's, and the record says so. Each repetition is a new study (seed = repetition)
in a fresh folder; the data set is generated once, into the cache, before the first (not timed).
Utilisation is sampled every 0.1-0.2 s (pynvml, else nvidia-smi; "n/a" without either) and assigned to
a phase by the phase times the study recorded, whose start is read to the second.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import Utilisation  # noqa: E402
from harness import ROOT, Bench, image_size, python_path  # noqa: E402

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


def export_gap(manifest: dict) -> float:
    """The largest |error as exported - error as the study reported| over the winner's paths (RMSE, m)."""
    study = manifest["source"]["study_path_metrics"]
    return max(abs(a["rmse"] - b["rmse"]) for a, b in zip(manifest["path_metrics"], study))


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
        run, plan, trials = stored.runs[-1], stored.plan or {}, len(study.trials)
        best, paper = winner(study), baseline_trial(study, "paper", retrained=True)
        exported = Path(tmp) / "winner" / "manifest.json"
        manifest = json.loads(exported.read_text()) if export_s is not None else None
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


def main() -> None:
    bench = Bench(__file__, "a whole study at the deployment size on one GPU: phases, utilisation, winner", __doc__)
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
    args = bench.parse_args(ap)
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


if __name__ == "__main__":
    main()
