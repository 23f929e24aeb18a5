"""Held-out measurements taken at the speed a calibration measured at. A machine whose speed changes
from outside (other loads, throttling) can run every graph much slower for a while; a timing taken in
such a spell says nothing about a profile fitted while it ran at its usual speed. The rule is the
probe's own (``SLOW``, ``REMEASURE_PASSES``, ``wait_until_calm`` of ``explorer.probe``). Used by
bench_devices.py and bench_runtime.py; ``note_steadiness`` puts what the rule did into the harness's
record."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple, Sequence, TypeVar

from explorer.probe import (DEFAULT_PROVIDER, REMEASURE_PASSES, SLOW, default_threads, fixed_graph_timer,
                            speed_layer, usual_speed, wait_until_calm)

T = TypeVar("T")


def speedometer(bundle: Path, results: dict) -> Callable[[], float]:
    """How much slower than during its calibration the machine runs now (1 = its usual speed then):
    the probe's two speed-check graphs (from the calibration's ``bundle`` and ``results``) timed
    again, each against its usual time in the calibration; the slower of the two."""
    speed = results["speed"]
    graphs = [(speed_layer(results["bundle"]["layers"])["file"], speed["ms"]), (speed["stage"], speed["stage_ms"])]
    timers = [(fixed_graph_timer(bundle / file, default_threads(), DEFAULT_PROVIDER), usual_speed(times))
              for file, times in graphs if file and times]
    return lambda: max(timer() / usual for timer, usual in timers)


class Steady(NamedTuple):
    """What ``steadily`` took: the result, how many times it was taken again, and how much slower than
    during the calibration the machine ran around the last time (the slower of the two checks; above
    ``1 + SLOW`` when it stayed slow past the re-timing, and the result with it)."""

    result: object
    again: int
    slowness: float

    def note(self) -> str:
        """'' at the calibration's speed, else a few words saying how slow the machine still ran."""
        return "" if self.slowness <= 1 + SLOW else f" (machine {self.slowness:.2f}x slow)"


def steadily(measure: Callable[[], T], slowness: Callable[[], float],
             combine: Callable[[T, T], T] = lambda kept, new: new) -> Steady:
    """``measure()`` between two ``slowness`` checks; taken again (after waiting for the machine to calm
    down) while either check ran ``SLOW`` or more slower than usual, at most ``REMEASURE_PASSES`` times.
    ``combine`` folds a new result into the kept one (default: the new one replaces it)."""
    kept = None
    for again in range(REMEASURE_PASSES + 1):
        before = slowness()
        got = measure()
        after = slowness()
        kept = got if kept is None else combine(kept, got)
        if max(before, after) <= 1 + SLOW or again == REMEASURE_PASSES:
            return Steady(kept, again, max(before, after))
        wait_until_calm(after, slowness, 1.0)
    raise AssertionError("unreachable")


def note_steadiness(bench, what: str, taken: Sequence[Steady]) -> None:
    """Notes in ``bench``'s record (a ``harness.Bench``) how often ``what`` was taken again, and how
    many of its results were still taken on a slow machine: a reader of the figures needs to know."""
    again = sum(s.again for s in taken)
    slow = sum(bool(s.note()) for s in taken)
    if again or slow:
        bench.note(f"{what}: taken again {again} times after the machine ran slow; {slow} of {len(taken)} still slow")
