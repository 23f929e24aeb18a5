"""Does the search earn its time at the length ``make search`` runs? bench_search_value's comparison of
the default search with random candidates retrained, at T = 900 s (``make search`` gives the search 960 s
less its setup) rather than 300: each repetition one seed, the two interleaved (their order rotates
from seed to seed), each given ``--time-s`` T seconds with everything it needs:

- ``default``: ``explorer search --time-limit T`` as ``make search`` runs it (the supernet trained
  inside T, TPE sampling its estimates, the finalists retrained, the envelope's networks in the time
  they leave), no baselines;
- ``random_retrained``: candidates drawn at random from the space, no estimate, retrained one after
  another with the finalists' recipe as ``make search`` asks for it (``--random-steps``, default 300
  steps, then the tuning at 224x224) until T is spent; the best measured one is the winner.

At 300 s random retraining had the lower median (bench_search_value), with a few more candidates
retrained than the search's supernet and finalists left room for; here the supernet trains longer and
the sampling covers more, and random retraining gets about three times the candidates.

Then each seed's winners, the paper design and the envelope's dedicated networks (``--envelope-networks``,
default 3) are retrained with a longer recipe (``--final-steps``, default 600: twice the finalists'
steps, then their tuning) and measured at the deployment size, as in bench_search_value, whose figures
this bench shares (``ratio_<strategy>``, ``envelope_ratio_<strategy>``, ``floor_ratio``, ...).

    OMP_NUM_THREADS=1 python benchmarks/bench_search_long.py [--reps 3] [--time-s 900]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_search_value import run_comparison  # noqa: E402
from harness import Bench  # noqa: E402

STRATEGIES = ("default", "random_retrained")


def main() -> None:
    bench = Bench(__file__, "the search against random retraining at make search's length", __doc__)
    run_comparison(bench, STRATEGIES, time_s=900.0, final_steps=600, random_steps=300,
                   random_steps_why="the finalists' recipe", envelope_networks=3)


if __name__ == "__main__":
    main()
