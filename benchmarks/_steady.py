"""Held-out measurements taken at the speed a calibration measured at: on a shared VM whose speed
changes from outside (this project's 2-core Zen 4 VM runs a while as if it had one core, every
graph 1.5-1.8x slower), a timing taken in such a spell says nothing about a profile fitted in calm.
The rule is the probe's own (``probe_script.SLOW``, ``REMEASURE_PASSES``, ``wait_until_calm``)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple, TypeVar

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
