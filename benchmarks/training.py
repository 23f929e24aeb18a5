"""Training speed: memory layout, the optimizer, threads, and the supernet's pace.

    python -m benchmarks.training --list
    python -m benchmarks.training --only NAME [its options]
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import statistics
import tempfile
import time
from pathlib import Path
from typing import Sequence

import torch

from explorer.data import open_dataset
from explorer.model import build_network
from explorer.space import SearchSpace, paper_candidate
from explorer.study.config import SearchConfig
from explorer.supernet import Supernet, largest_candidate, read_supernet, train_supernet
from explorer.supernet.pace import seconds_per_step
from explorer.training.cpu import busy_elsewhere, free_threads, usable_cores
from explorer.training.train import multi_exit_loss

from benchmarks.harness import Bench, Case, interleave, run_suite, time_interleaved


# -- layout -----------------------------------------------------------------------------------

LAYOUTS = {"contiguous": torch.contiguous_format, "channels_last": torch.channels_last}


def step(net, layout, largest, image, scan, depth) -> float:
    """Seconds of one forward and backward pass in ``layout``."""
    net.to(memory_format=layout)
    x = image.contiguous(memory_format=layout)
    t = time.perf_counter()
    outs = net.forward_subnet(largest, x, scan) if isinstance(net, Supernet) else net(x, scan)
    multi_exit_loss(outs, depth)[0].backward()
    return time.perf_counter() - t


def largest_difference(image, scan) -> float:
    net = build_network(paper_candidate()).eval()
    with torch.no_grad():
        a = net(image, scan)
        net.to(memory_format=torch.channels_last)
        b = net(image.contiguous(memory_format=torch.channels_last), scan)
    return max(float((p - q).abs().max()) for p, q in zip(a, b))


def bench_layout(argv: Sequence[str] | None = None) -> None:
    """Channels-last against the default memory layout for training: one training step (forward and
    backward, batch 16 at 64x64) of the paper design and of the supernet's largest subnet. PyTorch's CPU
    convolutions can be faster on channels-last tensors; this says whether training should use it here.

        python -m benchmarks.training --only layout [--reps 5]

    Both layouts alternate within each repetition; the largest output difference between the two layouts
    is in the record's notes.
    """
    bench = Bench("bench_layout", "Channels-last against contiguous layout: training step time",
                  bench_layout.__doc__, reps=5)
    bench.parse_args(bench.parser(), argv)
    torch.set_num_threads(2)
    torch.manual_seed(0)
    image, scan, depth = torch.rand(16, 3, 64, 64), torch.rand(16, 64) * 5, torch.rand(16, 1, 64, 64) * 5
    space = SearchSpace.from_yaml("anytime_depth")
    largest = largest_candidate(space)
    cases = {"paper": ("paper design", build_network(paper_candidate()).train()),
             "supernet": ("supernet largest subnet", Supernet(space).train())}
    for key, (label, net) in cases.items():
        for layout in LAYOUTS.values():   # warm-up
            step(net, layout, largest, image, scan, depth)
        bench.figure(f"{key}_contiguous_s", f"{label}, contiguous", "s", "lower")
        bench.figure(f"{key}_channels_last_s", f"{label}, channels-last", "s", "lower")
        bench.figure(f"{key}_speedup", f"{label}: contiguous / channels-last", "x", "higher")
    bench.note(f"largest output difference between layouts {largest_difference(image, scan):.1e} m; 2 threads")
    for rep in bench.repetitions():
        for key, (_, net) in cases.items():
            got = interleave({k: (lambda lay=lay: step(net, lay, largest, image, scan, depth))
                              for k, lay in LAYOUTS.items()}, rep)
            bench.add(f"{key}_contiguous_s", got["contiguous"])
            bench.add(f"{key}_channels_last_s", got["channels_last"])
            bench.add(f"{key}_speedup", got["contiguous"] / got["channels_last"])
    bench.finish()


# -- optimizer --------------------------------------------------------------------------------

def optimizers(device: torch.device) -> dict:
    """{"plain": AdamW with PyTorch's defaults, "fused": the fused AdamW}, each over its own copy of the
    supernet's parameters, every one with a gradient."""
    out = {}
    for name, fused in (("plain", None), ("fused", True)):
        torch.manual_seed(0)
        params = list(Supernet(SearchSpace.from_yaml("anytime_depth")).to(device).parameters())
        for p in params:
            p.grad = torch.randn_like(p) * 1e-3
        out[name] = torch.optim.AdamW(params, lr=2e-3, weight_decay=1e-4, fused=fused)
    return out


def bench_optimizer(argv: Sequence[str] | None = None) -> None:
    """The optimizer step of supernet training: PyTorch's AdamW as it comes (a loop over the tensors on
    the CPU, grouped "foreach" kernels on CUDA) against the fused AdamW that training uses
    (:func:`explorer.training.train.adamw`), over the default space's supernet parameters with gradients
    on every tensor.

        python -m benchmarks.training --only optimizer [--reps 3] [--device cpu|cuda] [--threads 2]

    Each repetition times both, in an order that rotates (10 rounds of 4 timed steps each, the median),
    and records milliseconds a step and their ratio.
    """
    bench = Bench("bench_optimizer", "AdamW step over the supernet's parameters: as it comes and fused",
                  bench_optimizer.__doc__)
    ap = bench.parser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, default=2, help="torch threads on the CPU")
    args = bench.parse_args(ap, argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    opts = optimizers(device)

    def stepper(opt):
        def step():
            opt.step()
            if device.type == "cuda":
                torch.cuda.synchronize()
        return step

    fns = {name: stepper(opt) for name, opt in opts.items()}
    n = sum(p.numel() for p in opts["plain"].param_groups[0]["params"])
    bench.note(f"{len(opts['plain'].param_groups[0]['params'])} tensors, {n / 1e6:.2f} M parameters, on {device}")
    plain = bench.figure("plain_ms", "AdamW as it comes", "ms", "lower")
    fused = bench.figure("fused_ms", "fused AdamW", "ms", "lower")
    ratio = bench.figure("speedup", "as it comes / fused", "x", "higher")
    for rep in bench.repetitions():
        ms = time_interleaved(fns, rep)
        bench.add(plain, ms["plain"])
        bench.add(fused, ms["fused"])
        bench.add(ratio, ms["plain"] / ms["fused"])
    bench.finish()


# -- threads ----------------------------------------------------------------------------------

def _spin() -> None:
    while True:
        pass


def step_ms(threads: int, steps: int) -> float:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = build_network(paper_candidate()).to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), 1e-3)
    image = torch.rand(16, 3, 64, 64).to(memory_format=torch.channels_last)
    scan = torch.rand(16, 64)

    def step() -> None:
        sum(o.mean() for o in net(image, scan)).backward()
        opt.step()
        opt.zero_grad()

    for _ in range(2):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return 1000 * (time.perf_counter() - t0) / steps


def bench_threads(argv: Sequence[str] | None = None) -> None:
    """PyTorch's CPU threads when other processes keep cores busy: a training step of the paper design
    (64x64, batch 16, AdamW, channels-last) on every core against one thread per core left free, beside
    0, 1 and 2 CPU-bound processes. What a training command does (:mod:`explorer.training.cpu`) is the
    second: it counts the cores others keep busy and leaves them out.

        python -m benchmarks.training --only threads [--reps 3] [--steps 15] [--loads 0,1,2]

    Each repetition times both thread counts at every load, in an order that rotates; a timing is the
    mean of ``--steps`` steps after two untimed ones. Beside 0 loads both counts are every core.
    """
    bench = Bench("bench_threads", "CPU threads beside other work: every core against the free ones",
                  bench_threads.__doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--loads", default="0,1,2", help="CPU-bound processes beside it, comma-separated")
    args = bench.parse_args(ap, argv)
    cores, loads = torch.get_num_threads(), [int(n) for n in args.loads.split(",")]
    bench.note(f"{len(usable_cores())} usable cores; PyTorch's default {cores} threads")
    for n in loads:
        bench.figure(f"all_{n}_ms", f"beside {n} load(s): {cores} threads, a step", "ms", "lower")
        bench.figure(f"free_{n}_ms", f"beside {n} load(s): threads on the free cores, a step", "ms", "lower")
        bench.figure(f"speedup_{n}", f"beside {n} load(s): all threads / free threads", "x", "higher")
    for rep in bench.repetitions():
        for n in loads:
            spinners = [mp.get_context("fork").Process(target=_spin, daemon=True) for _ in range(n)]
            for p in spinners:
                p.start()
            try:
                time.sleep(0.5)
                free = min(cores, free_threads(len(usable_cores()), busy_elsewhere() or 0.0))
                print(f"  beside {n} load(s): {free} free thread(s)")
                got = interleave({"all": lambda: step_ms(cores, args.steps),
                                  "free": lambda: step_ms(free, args.steps)}, rep)
            finally:
                for p in spinners:
                    p.terminate()
            bench.add(f"all_{n}_ms", got["all"])
            bench.add(f"free_{n}_ms", got["free"])
            bench.add(f"speedup_{n}", got["all"] / got["free"])
    bench.finish()


# -- supernet_pace ----------------------------------------------------------------------------

SHORT_RUN_STEPS = 6


def short_run(space: SearchSpace, data: str, recipe, folder: Path) -> float:
    """The median step of a 6-step run of ``recipe`` after its first two (the step times from the progress
    marks, as they come one step late)."""
    marks: dict[int, float] = {}
    train_supernet(space, data, dataclasses.replace(recipe, steps=SHORT_RUN_STEPS), folder / "short.pt",
                   torch.device("cpu"), progress=lambda s, n, r: marks.setdefault(s, time.perf_counter()))
    (folder / "short.pt").unlink()
    steps = sorted(marks)
    return statistics.median(marks[b] - marks[a] for a, b in zip(steps, steps[1:]) if a >= 2)


def whole_recipe(space: SearchSpace, data: str, recipe, folder: Path) -> float:
    """The seconds a step of the whole ``recipe``, as its file records its training time."""
    out = train_supernet(space, data, recipe, folder / "whole.pt", torch.device("cpu"))
    state = read_supernet(out)
    out.unlink()
    return float(state["seconds"]) / int(state["step"])


def bench_supernet_pace(argv: Sequence[str] | None = None) -> None:
    """How well a time limit's plan knows what its supernet will take: the seconds a step as the plan
    measures it (``explorer.supernet.pace.seconds_per_step``: a few steps of each phase of the recipe,
    weighted by their share), as a short run of the recipe reads it (its first 6 steps, the median after
    the first two: mostly the second phase, where progressive shrinking no longer keeps every width full),
    and as the whole recipe takes it (its wall time over its steps, data loading aside).

        python -m benchmarks.training --only supernet_pace [--reps 3] [--steps 300] [--threads 2]

    Each repetition runs the two measurements and the whole recipe one after the other, their order turning
    from one repetition to the next, on the default space and data (generated before anything is timed).
    """
    bench = Bench("bench_supernet_pace", "the supernet's step time: the plan's measurement against the whole recipe",
                  bench_supernet_pace.__doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=300, help="the whole recipe's steps (default 300)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = bench.parse_args(ap, argv)
    torch.set_num_threads(args.threads)
    space, config = SearchSpace.from_yaml("anytime_depth"), SearchConfig(study="supernet-pace")
    recipe = dataclasses.replace(config.supernet_recipe(), steps=args.steps)
    open_dataset(config.data, "train", recipe.input_size, seed=recipe.seed)
    bench.figure("whole_step_s", f"the whole recipe ({args.steps} steps): seconds a step", "s")
    bench.figure("phases_step_s", "the plan's measurement (both phases, weighted): seconds a step", "s")
    bench.figure("short_run_step_s", f"a {SHORT_RUN_STEPS}-step run's median step", "s")
    bench.figure("phases_ratio", "the plan's measurement / the whole recipe's", "")
    bench.figure("short_run_ratio", f"the {SHORT_RUN_STEPS}-step run's / the whole recipe's", "")
    with tempfile.TemporaryDirectory(prefix="bench-supernet-pace-") as tmp:
        for rep in bench.repetitions():
            got = interleave({"phases": lambda: seconds_per_step(space, config.data, recipe, torch.device("cpu")),
                              "short_run": lambda: short_run(space, config.data, recipe, Path(tmp)),
                              "whole": lambda: whole_recipe(space, config.data, recipe, Path(tmp))}, rep)
            for name, value in got.items():
                bench.add(f"{name}_step_s", value)
            for name in ("phases", "short_run"):
                bench.add(f"{name}_ratio", got[name] / got["whole"])
    bench.note(f"cpu, torch threads {args.threads}; the default space, data and supernet recipe with {args.steps} "
               "steps")
    bench.finish()


CASES = (Case(bench_layout), Case(bench_optimizer), Case(bench_threads), Case(bench_supernet_pace))

if __name__ == "__main__":
    run_suite(CASES)
