"""Timing several ways of doing one thing on a machine whose speed changes from one second to the
next (a shared VM): short blocks of calls of each, in turn, so that all of them see the same states."""

from __future__ import annotations

import random
import statistics
import time
from typing import Callable

_ORDERS = random.Random(0)   # one sequence of orders per process: repeatable, and new for every call


def time_interleaved(fns: dict[str, Callable[[], object]], blocks: int = 10, per_block: int = 4) -> dict[str, float]:
    """The median wall time in ms of each of ``fns`` over ``blocks`` rounds; in each round every
    function runs once untimed (its buffers back in the caches after the others') and ``per_block``
    times timed. The order changes from round to round (seeded): what ran just before a function can
    slow or speed it (the caches it left, threads of another library still spinning), and a fixed order
    would charge that to the same function every time."""
    samples: dict[str, list[float]] = {name: [] for name in fns}
    order = list(fns)
    for _ in range(blocks):
        _ORDERS.shuffle(order)
        for name in order:
            fn = fns[name]
            fn()
            for _ in range(per_block):
                t0 = time.perf_counter()
                fn()
                samples[name].append((time.perf_counter() - t0) * 1000.0)
    return {name: statistics.median(s) for name, s in samples.items()}
