"""Timing several ways of doing one thing on a machine whose speed changes from one second to the
next (a shared VM): short blocks of calls of each, in turn, so that all of them see the same states."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def time_interleaved(fns: dict[str, Callable[[], object]], blocks: int = 10, per_block: int = 4) -> dict[str, float]:
    """The median wall time in ms of each of ``fns`` over ``blocks`` rounds; in each round every
    function runs once untimed (its buffers back in the caches after the others') and ``per_block``
    times timed."""
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(blocks):
        for name, fn in fns.items():
            fn()
            for _ in range(per_block):
                t0 = time.perf_counter()
                fn()
                samples[name].append((time.perf_counter() - t0) * 1000.0)
    return {name: statistics.median(s) for name, s in samples.items()}
