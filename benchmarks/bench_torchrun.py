"""Data-parallel supernet training under ``torchrun`` against one process that computes the same
update: N processes on this machine's device(s) (on one GPU they share it and reduce through gloo;
with a GPU each, NCCL), against one process with ``--micro-batches N``. Figures: each one's time per
step, the speed-up, and whether the two trained supernets are equally good: the ratio of their
validation losses on the same subnets and frames, and the largest parameter difference. The same
updates computed two ways differ by rounding alone, but the first steps of Adam turn rounding into
lr-sized steps wherever a gradient is near zero (a relative 1e-7 change of the initial weights moves
most of the default space's parameters by over 1e-5 within 3 steps), so the loss ratio, near 1, is
the measure; the suite checks bit-level agreement on the tiny space.

    python benchmarks/bench_torchrun.py                           # 2 processes, the GPU where there is one
    python benchmarks/bench_torchrun.py --nproc 2 --size 224x224 --batch-size 64
    python benchmarks/bench_torchrun.py --device cpu --steps 3 --warmup-steps 1 --size 32x32 --batch-size 8 \\
        --data synthetic:32:16 --reps 1 --no-record               # a smoke run

Step times are the median of a run's last --steps steps after --warmup-steps untimed ones (the first
steps capture the stages' CUDA graphs and make cuDNN's plans), read by the first process. Both runs
train the same recipe from the same seed, every width from the first step, in an order that turns
over from one repetition to the next. On a CPU each of the N processes gets 1/N of the cores.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import cores, subnet_losses, train_steps  # noqa: E402
from harness import ROOT, Bench, image_size, interleave, python_path  # noqa: E402


def worker(args) -> None:
    """One process of a run: trains, saves the supernet to --weights; the first writes its step time."""
    seconds = train_steps(args.device, args.size, args.batch_size, args.steps, args.data, amp=False,
                          out=Path(args.weights), warm=args.warmup_steps, micro_batches=args.micro_batches)
    if int(os.environ.get("RANK", "0")) == 0:
        Path(args.worker).write_text(json.dumps({"step_s": seconds}))


def run(args, nproc: int, folder: Path) -> tuple[float, Path]:
    """(median step seconds, supernet file) of ``nproc`` processes under torchrun, or of one process
    with ``--micro-batches`` = ``args.nproc`` when ``nproc`` is 1."""
    times, weights = folder / f"times-{nproc}.json", folder / f"supernet-{nproc}.pt"
    size = f"{args.size[0]}x{args.size[1]}"
    script = [str(Path(__file__).resolve()), "--worker", str(times), "--weights", str(weights), "--device",
              args.device, "--steps", str(args.steps), "--warmup-steps", str(args.warmup_steps), "--data", args.data,
              "--size", size, "--batch-size", str(args.batch_size),
              "--micro-batches", str(args.nproc if nproc == 1 else 1)]
    launch = [sys.executable] + (["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc)]
                                 if nproc > 1 else [])
    env = {**os.environ, "PYTHONPATH": python_path()}
    if args.device == "cpu":
        env["OMP_NUM_THREADS"] = str(max(1, cores() // nproc))
    proc = subprocess.run(launch + script, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{nproc} process(es) failed:\n{proc.stderr[-3000:]}")
    return json.loads(times.read_text())["step_s"], weights


def apart(args, one: Path, many: Path) -> tuple[float, float]:
    """(validation loss of the torchrun supernet / the one process's, over the same subnets and frames;
    largest parameter difference, BatchNorm's running statistics left out: they are per process)."""
    import statistics
    import torch
    sa, sb = (torch.load(f, weights_only=True, map_location="cpu")["state_dict"] for f in (one, many))
    keys = [k for k in sa if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    largest = max(float((sa[k].float() - sb[k].float()).abs().max()) for k in keys)
    single, parallel = subnet_losses([one, many], args.device, args.data, args.size)
    return statistics.fmean(parallel) / statistics.fmean(single), largest


def main() -> None:
    bench = Bench(__file__, "torchrun's processes against one process with the same micro-batches", __doc__)
    ap = bench.parser()
    ap.add_argument("--nproc", type=int, default=2, help="processes under torchrun (default 2)")
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    ap.add_argument("--size", type=image_size, default=(64, 64), help="training size (default 64x64)")
    ap.add_argument("--batch-size", type=int, default=16, help="global batch (default 16)")
    ap.add_argument("--steps", type=int, default=20, help="timed steps (default 20)")
    ap.add_argument("--warmup-steps", type=int, default=10, help="untimed steps before them (default 10)")
    ap.add_argument("--data", default="synthetic:400:100", help="data set (default synthetic:400:100)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--weights", help=argparse.SUPPRESS)
    ap.add_argument("--micro-batches", type=int, default=1, help=argparse.SUPPRESS)
    args = bench.parse_args(ap)
    if args.worker:
        return worker(args)
    import torch
    args.device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    from explorer.data import open_dataset
    open_dataset(args.data, "train", args.size)   # generated once, before the timing
    n = args.nproc
    bench.figure("step_s_one_process", f"one process, --micro-batches {n}", "s", "lower")
    bench.figure("step_s_torchrun", f"{n} processes under torchrun", "s", "lower")
    bench.figure("speedup", f"one process / {n} processes, step time", "x", "higher")
    bench.figure("loss_ratio", f"validation L1, {n} processes' supernet / one process's", "x")
    bench.figure("params_max_difference", "largest parameter difference", "", "lower")
    where = torch.cuda.get_device_name() if args.device == "cuda" else "CPU"
    bench.note(f"{where}, {torch.cuda.device_count() if args.device == 'cuda' else 0} GPU(s); {n} processes; "
               f"{args.size[0]}x{args.size[1]}, global batch {args.batch_size}; {args.steps} steps timed after "
               f"{args.warmup_steps}; data {args.data}")
    for rep in bench.repetitions():
        with tempfile.TemporaryDirectory() as tmp:
            got = interleave({k: (lambda k=k: run(args, k, Path(tmp))) for k in (1, n)}, rep)
            bench.add("step_s_one_process", got[1][0])
            bench.add("step_s_torchrun", got[n][0])
            bench.add("speedup", got[1][0] / got[n][0])
            ratio, largest = apart(args, got[1][1], got[n][1])
            bench.add("loss_ratio", ratio)
            bench.add("params_max_difference", largest)
    bench.finish()


if __name__ == "__main__":
    main()
