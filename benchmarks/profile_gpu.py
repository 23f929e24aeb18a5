"""Where a supernet step and a supernet search spend their time on this machine's device (CUDA where
PyTorch sees a GPU, else the CPU). Not a benchmark: it records nothing, it says where to look.

    python benchmarks/profile_gpu.py --out profile/
    python benchmarks/profile_gpu.py --device cpu --steps 4 --search-seconds 10 --out profile/

Writes to --out:
- ``step_<recipe>.txt``: torch.profiler's operators over --steps supernet steps (after --warmup-steps
  untimed ones and 3 more in the same run, every width training from the start)
  at the default recipe (64x64, batch 16) and at the GPU recipe (224x224, batch 64, bf16 on CUDA),
  by their own host time and by their own device time, with the wall time per step and the device's
  busy share (its kernels' time over the wall time);
- ``search.txt``: cProfile's functions of a supernet search sampling --search-seconds (its supernet
  trained beforehand), by cumulative and by own time.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import search_config  # noqa: E402

RECIPES = {"default": ((64, 64), 16, False), "gpu": ((224, 224), 64, True)}


def profile_steps(device: str, name: str, steps: int, data: str, out: Path, warmup: int = 0) -> str:
    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile, schedule
    from explorer.space import SearchSpace
    from explorer.supernet import SupernetRecipe, train_supernet
    size, batch, amp = RECIPES[name]
    # the untimed steps run first in the same run (every width from the start, as bench_gpu times), so
    # that its stage graphs are captured and cuDNN's plans made before the profile: a long run's state
    recipe = SupernetRecipe(steps=warmup + 3 + steps, batch_size=batch, input_size=size,
                            amp=amp and device == "cuda", shrink=0.0)
    space = SearchSpace.from_yaml("anytime_depth")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    marks: list[float] = []
    with profile(activities=activities, schedule=schedule(wait=warmup, warmup=3, active=steps, repeat=1)) as prof:
        def progress(step, total, record):
            marks.append(time.perf_counter())
            prof.step()
        with tempfile.TemporaryDirectory() as tmp:
            train_supernet(space, data, recipe, Path(tmp) / "s.pt",
                           torch.device(device), progress=progress, checkpoint_every=10**9)
    marks = marks[warmup:]
    wall = (marks[3 + steps - 1] - marks[2]) / steps if len(marks) >= 3 + steps else float("nan")
    events = prof.key_averages()
    # the kernels alone, as the table's total counts them: a step's annotation spans its kernels
    busy = sum(e.self_device_time_total for e in events
               if e.device_type == DeviceType.CUDA and not getattr(e, "is_user_annotation", False)
               and not e.key.startswith("ProfilerStep")) / 1e6 / steps
    head = (f"{name}: {size[0]}x{size[1]}, batch {batch}, bf16 {recipe.amp}, {device}, after {warmup} steps\n"
            f"wall per step {wall:.4f} s; device kernels per step {busy:.4f} s; busy share "
            f"{busy / wall if wall == wall and wall > 0 else float('nan'):.2f}\n")
    text = head + "\n-- by own host time --\n" + events.table(sort_by="self_cpu_time_total", row_limit=30)
    if device == "cuda":
        text += "\n-- by own device time --\n" + events.table(sort_by="self_device_time_total", row_limit=30)
    (out / f"step_{name}.txt").write_text(text)
    return head


def profile_search(device: str, data: str, seconds: float, out: Path) -> str:
    import optuna
    from explorer.study.search import ensure_supernet, search
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    config = search_config("gpu-profile", device, data, 30)
    ensure_supernet(config.resolve())
    prof = cProfile.Profile()
    with tempfile.TemporaryDirectory() as tmp:
        prof.enable()
        outcome = search(config, n_trials=None, timeout_s=seconds, reports=Path(tmp))
        prof.disable()
        done = sum(t.state.name == "COMPLETE" for t in outcome.study.get_trials())
    text = io.StringIO()
    for key, limit in (("cumulative", 45), ("tottime", 30)):
        text.write(f"\n-- by {key} --\n")
        pstats.Stats(prof, stream=text).sort_stats(key).print_stats(limit)
    head = f"search: {done} trials in {seconds:g} s of sampling on {device}\n"
    (out / "search.txt").write_text(head + text.getvalue())
    return head


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for the profiles (made if missing)")
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    ap.add_argument("--steps", type=int, default=8, help="profiled supernet steps per recipe (default 8)")
    ap.add_argument("--warmup-steps", type=int, default=60, help="untimed steps per recipe before its profile, "
                    "in the same run (default 60: its stage graphs captured, cuDNN's plans made)")
    ap.add_argument("--search-seconds", type=float, default=15.0, help="sampling time of the profiled search")
    ap.add_argument("--recipes", default="default,gpu", help="recipes to profile (default: default,gpu; '' for none)")
    ap.add_argument("--data", default="synthetic:400:100", help="data set (default synthetic:400:100)")
    args = ap.parse_args()
    import torch
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    args.out.mkdir(parents=True, exist_ok=True)
    for name in filter(None, args.recipes.split(",")):   # --recipes '' profiles the search alone
        print(profile_steps(device, name, args.steps, args.data, args.out, args.warmup_steps), flush=True)
    print(profile_search(device, args.data, args.search_seconds, args.out), flush=True)


if __name__ == "__main__":
    main()
