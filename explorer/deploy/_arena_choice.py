"""Which of two equivalent sets of stage sessions a run of ``AnytimeRunner`` uses.

Stage sessions that allocate from one shared memory arena reuse each other's buffers: the next stage
writes where the last one just wrote. Whether that pays depends on the machine's state, and on a
machine shared with other loads that state changes from outside every few seconds: with the cores
free the staged chain runs faster with the shared arena, with them contended it can run faster with
an arena per session. Neither set
is best in both states, so the runner keeps both and measures them as it runs: a run uses the shared
arena's set unless the other took ``MARGIN`` less time lately (the median of each stage's last
``WINDOW`` timings), and the other set for ``EXPLORE_RUNS`` runs in a row, ``EXPLORE_EVERY`` runs after
the choice last changed, then at twice the last interval each time it stays (up to
``EXPLORE_EVERY_MAX``), so that a change of state is seen within a few hundred runs and a machine where
one set stays faster pays little for looking (exploring at a fixed pace would keep running the slower
set a fixed share of the time). Only a run that follows a run of the same set counts: the first run
after a switch finds the other set's buffers in the caches. So chosen, the runner keeps up with the
better set in each state, where taking whichever set looked faster ran the worse one much of the time
(the runner as shipped against each set held).
"""

from __future__ import annotations

import statistics
from collections import deque

#: this many runs after the choice changed, the set not in favour is timed again ...
EXPLORE_EVERY = 50
#: ... for this many runs in a row (the first of them only warms it); then again after twice the
#: interval, as long as the choice stays, up to this many runs apart
EXPLORE_EVERY_MAX = 400
EXPLORE_RUNS = 3
#: a set's time for a stage: the median of its last this many warm timings
WINDOW = 5
#: another set takes over from the first (the shared arena's) only when it is this much faster
MARGIN = 0.05


class ArenaChoice:
    """Recent warm timings of every stage in each of ``options`` session sets; ``pick`` the set for the
    next run, ``record`` the stages it completed."""

    def __init__(self, options: int, stages: int) -> None:
        self.samples = [[deque(maxlen=WINDOW) for _ in range(stages)] for _ in range(options)]
        self.runs = [0] * options   # how many runs each set served
        self._count = 0
        self._last: int | None = None
        self._warm = False   # whether the run picked last follows one of the same set
        self._favoured: int | None = None   # the set ``best`` gave last
        self._every = EXPLORE_EVERY         # the interval before the coming exploration
        self._explore_at = EXPLORE_EVERY - EXPLORE_RUNS + 1   # the run that starts it

    def ms(self, option: int, stage: int) -> "float | None":
        """The set's time for the stage (the median of its recent warm timings); None before any."""
        recent = self.samples[option][stage]
        return statistics.median(recent) if recent else None

    def best(self) -> int:
        """The first set, unless another took ``MARGIN`` less total time over the stages every set has
        timed; before that, the one with the fewest stages timed (so that it gets timed)."""
        options, stages = range(len(self.samples)), range(len(self.samples[0]))
        common = [k for k in stages if all(self.samples[o][k] for o in options)]
        if not common:
            return min(options, key=lambda o: sum(bool(s) for s in self.samples[o]))
        total = [sum(self.ms(o, k) for k in common) for o in options]
        fastest = min(options, key=total.__getitem__)
        return fastest if total[fastest] < (1 - MARGIN) * total[0] else 0

    def pick(self) -> int:
        self._count += 1
        option = self.best()
        other = (option + 1) % len(self.samples)   # a runner has one or two sets
        if self._count == self._explore_at + EXPLORE_RUNS:   # an exploration just ended: when the next one
            if option != self._favoured or self._latest_faster(other, option):
                self._every = EXPLORE_EVERY   # the choice changed, or may soon: look again soon
            self._explore_at = self._count + self._every - EXPLORE_RUNS
            self._every = min(2 * self._every, EXPLORE_EVERY_MAX)
        elif option != self._favoured:   # changed on the favoured set's own timings
            self._every = EXPLORE_EVERY
            self._explore_at = min(self._explore_at, self._count + EXPLORE_EVERY - EXPLORE_RUNS)
        self._favoured = option
        if self._explore_at <= self._count < self._explore_at + EXPLORE_RUNS:
            option = other
        self._warm, self._last = option == self._last, option
        self.runs[option] += 1
        return option

    def _latest_faster(self, option: int, than: int) -> bool:
        """Whether the latest warm timings of ``option`` took ``MARGIN`` less than ``than``'s recent ones,
        over the stages both have timed: its median may not show it yet."""
        common = [k for k in range(len(self.samples[0])) if self.samples[option][k] and self.samples[than][k]]
        latest = sum(self.samples[option][k][-1] for k in common)
        return bool(common) and latest < (1 - MARGIN) * sum(self.ms(than, k) for k in common)

    def record(self, option: int, stage: int, ms: float) -> None:
        """A stage of the run ``pick`` gave ``option`` took ``ms``; kept if that run was warm."""
        if self._warm:
            self.samples[option][stage].append(ms)
