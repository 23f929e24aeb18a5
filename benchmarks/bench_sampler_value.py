"""Does TPE earn its place at the length ``make search`` runs? bench_search_value's comparison of the
default search with the same search sampling at random, at T = 900 s (``make search`` gives the search
960 s less its setup) rather than 300, where the two were level within the noise: each repetition one
seed, the two interleaved (their order rotates from seed to seed), each given ``--time-s`` T seconds
with everything it needs:

- ``default``: ``explorer search --time-limit T`` as ``make search`` runs it (the supernet trained
  inside T, Optuna's TPE sampling its estimates, the finalists retrained, the envelope's networks in
  the time they leave), no baselines;
- ``random_sampling``: the same with ``--sampler random`` (uniform sampling of the same supernet
  recipe's estimates).

Then each seed's two winners, the paper design and the envelope's dedicated networks
(``--envelope-networks``, default 3) are retrained with a longer recipe (``--final-steps``, default 600:
twice the finalists' steps, then their tuning) and measured at the deployment size, as in
bench_search_value, whose figures this bench shares (``ratio_<strategy>``, ``lead_random_sampling``:
random sampling's ratio minus the default's in the same seed, ``envelope_ratio_<strategy>``,
``floor_ratio``, ...).

    OMP_NUM_THREADS=1 python benchmarks/bench_sampler_value.py [--reps 3] [--time-s 900] [--first-seed 0]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_search_value import run_comparison  # noqa: E402
from harness import Bench  # noqa: E402

STRATEGIES = ("default", "random_sampling")


def main() -> None:
    bench = Bench(__file__, "TPE against random sampling at make search's length", __doc__)
    run_comparison(bench, STRATEGIES, time_s=900.0, final_steps=600, envelope_networks=3)


if __name__ == "__main__":
    main()
