"""Which of two equivalent sets of stage sessions a run of ``AnytimeRunner`` uses.

Stage sessions that allocate from one shared memory arena reuse each other's buffers: the next stage
writes where the last one just wrote. Whether that pays depends on the machine's state, and on this
project's 2-core Zen 4 VM that state changes from outside every 10-30 s: calm, the paper design's
whole graph takes 7.7 ms and its staged chain ran +0.9% over it with the shared arena, +7.1% with an
arena per session; slowed (whole graph 13.9 ms, two threads no faster than one), +14.8% shared and
-6.6% with arenas of their own (about 120 runs in each state, interleaved; measured with the paper
design's stage graphs as ``benchmarks/bench_runtime.py`` makes them). Neither set is within 5% in both
states, so the runner keeps both and measures them as it runs: a run uses the set whose stages took
less time lately, and every ``EXPLORE_EVERY``-th run the other one, so that a change of state is seen
within a few dozen runs.
"""

from __future__ import annotations

#: every this many runs, the set not in favour is timed again
EXPLORE_EVERY = 8
#: weight of the newest timing in a stage's running average
ALPHA = 0.5


class ArenaChoice:
    """Running average of every stage's time in each of ``options`` session sets; ``pick`` the set for
    the next run, ``record`` the stages it completed."""

    def __init__(self, options: int, stages: int) -> None:
        self.ms: list[list[float | None]] = [[None] * stages for _ in range(options)]
        self.runs = [0] * options   # how many runs each set served
        self._count = 0

    def best(self) -> int:
        """The set with the least total time over the stages every set has timed; before that, the
        one with the fewest stages timed (so that it gets timed)."""
        common = [k for k in range(len(self.ms[0])) if all(ms[k] is not None for ms in self.ms)]
        if not common:
            return min(range(len(self.ms)), key=lambda o: sum(m is not None for m in self.ms[o]))
        return min(range(len(self.ms)), key=lambda o: sum(self.ms[o][k] for k in common))

    def pick(self) -> int:
        self._count += 1
        option = self.best()
        if len(self.ms) > 1 and self._count % EXPLORE_EVERY == 0:
            option = (option + 1 + (self._count // EXPLORE_EVERY) % (len(self.ms) - 1)) % len(self.ms)
        self.runs[option] += 1
        return option

    def record(self, option: int, stage: int, ms: float) -> None:
        old = self.ms[option][stage]
        self.ms[option][stage] = ms if old is None else old + ALPHA * (ms - old)
