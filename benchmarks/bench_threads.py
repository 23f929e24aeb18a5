"""PyTorch's CPU threads when other processes keep cores busy: a training step of the paper design
(64x64, batch 16, AdamW, channels-last) on every core against one thread per core left free, beside
0, 1 and 2 CPU-bound processes. What a training command does (:mod:`explorer.training.cpu`) is the
second: it counts the cores others keep busy and leaves them out.

    python benchmarks/bench_threads.py [--reps 3] [--steps 15] [--loads 0,1,2]

Each repetition times both thread counts at every load, in an order that rotates; a timing is the
mean of ``--steps`` steps after two untimed ones. Beside 0 loads both counts are every core.
"""

import multiprocessing as mp
import time

import torch

from explorer.model import build_network
from explorer.space import paper_candidate
from explorer.training.cpu import busy_elsewhere, free_threads, usable_cores

from harness import Bench, interleave


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


if __name__ == "__main__":
    bench = Bench(__file__, "CPU threads beside other work: every core against the free ones", __doc__)
    ap = bench.parser()
    ap.add_argument("--steps", type=int, default=15)
    ap.add_argument("--loads", default="0,1,2", help="CPU-bound processes beside it, comma-separated")
    args = bench.parse_args(ap)
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
