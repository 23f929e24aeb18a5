"""How many threads PyTorch's CPU kernels use: the cores other work leaves free.

PyTorch runs a kernel on all its threads and waits for the last one at the end. On a machine where
other processes keep cores busy (a robot's other nodes, a second job on a shared box), a thread the
scheduler has set aside holds the others up at every kernel, and a training step beside one or two
CPU-bound processes takes about twice as long on every core as on the free ones
(``bench_threads``). So a training command starts with as many threads as there are
cores nobody else is using, measured over half a second, at least one and at most PyTorch's default. ``OMP_NUM_THREADS``
(or ``MKL_NUM_THREADS``) set by the user, or by ``torchrun``, is left alone.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

PROC_STAT = Path("/proc/stat")
WINDOW_S = 0.5


def usable_cores() -> list[int]:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def _busy_ticks(cores: list[int]) -> int | None:
    """Clock ticks the given cores have spent working (not idle, not waiting on I/O), from /proc/stat."""
    try:
        lines = PROC_STAT.read_text().splitlines()
    except OSError:
        return None
    wanted, busy = {f"cpu{c}" for c in cores}, 0
    for line in lines:
        name, *ticks = line.split()
        if name in wanted and len(ticks) >= 5:
            values = [int(t) for t in ticks[:8]]
            busy += sum(values) - values[3] - values[4]    # idle and iowait are the 4th and 5th
    return busy


def busy_elsewhere(window_s: float = WINDOW_S) -> float | None:
    """How many of this process's cores other processes kept busy over ``window_s`` seconds (None
    where the kernel does not say: no /proc/stat)."""
    cores = usable_cores()
    before, own_before, t0 = _busy_ticks(cores), time.process_time(), time.monotonic()
    if before is None:
        return None
    time.sleep(window_s)
    after, own_after, t1 = _busy_ticks(cores), time.process_time(), time.monotonic()
    if after is None:
        return None
    seconds = (after - before) / os.sysconf("SC_CLK_TCK") - (own_after - own_before)
    return max(seconds / max(t1 - t0, 1e-6), 0.0)


def free_threads(cores: int, busy: float) -> int:
    """Threads for ``cores`` cores of which ``busy`` are taken: a core counts as taken from 0.6 of it."""
    return max(1, min(cores, cores - int(busy + 0.4)))


def use_free_cores() -> tuple[int, float | None]:
    """Sets PyTorch's intra-op threads to the free cores (unless the environment fixes them);
    returns (threads, cores busy elsewhere or None when not measured)."""
    import torch
    if os.environ.get("OMP_NUM_THREADS") or os.environ.get("MKL_NUM_THREADS"):
        return torch.get_num_threads(), None
    busy = busy_elsewhere()
    if busy is None:
        return torch.get_num_threads(), None
    threads = min(torch.get_num_threads(), free_threads(len(usable_cores()), busy))
    torch.set_num_threads(threads)
    return threads, busy
