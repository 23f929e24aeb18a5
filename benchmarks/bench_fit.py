"""The host fit (``fit_results``: every layer and stage graph a calibration timed, fp32 and int8,
the body exponent's grid) with the observations priced as one batch of arrays
(``explorer.cost.fit.ObservationBatch``, HEAD) against one Python call per workload (the rule until
stop 39), on the same measurements, interleaved: every repetition and the median, and how far the
two fitted profiles' predictions for the paper design lie apart.

    .venv/bin/python benchmarks/bench_fit.py [--results calibration.json] [--reps 3]

Without ``--results`` it first calibrates this machine quickly (``explorer calibrate --quick``'s sweep,
about 2 min) for measurements to fit.
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import explorer.cost.fit as fit
from explorer.cost import candidate_cost
from explorer.calibration.calibrate import calibrate, fit_results, read_results
from explorer.space import paper_candidate


class _OneByOne:
    """The pricing until stop 39: ``predict_ms`` for each observation, ``layer_ms`` for each workload."""

    def __init__(self, observations) -> None:
        self.observations = list(observations)

    def predict_ms(self, profile) -> np.ndarray:
        return np.array([fit.predict_ms(profile, o) for o in self.observations])


def _fit(results: dict, batch: type) -> tuple[float, object]:
    kept, fit.ObservationBatch = fit.ObservationBatch, batch
    try:
        t0 = time.perf_counter()
        prof = fit_results(results)
        return time.perf_counter() - t0, prof
    finally:
        fit.ObservationBatch = kept


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--results", type=Path, help="a calibration's probe results (bench_devices.py --save keeps them)")
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.results
        if path is None:
            path = Path(tmp) / "calibration.json"
            print("calibrating this machine (quick sweep) for measurements to fit ...", flush=True)
            calibrate(scale=0.35, repeats=5, energy=False, results_out=path)
        results = read_results(path)
    variants = {"batch (HEAD)": fit.ObservationBatch, "one by one": _OneByOne}
    times: dict[str, list[float]] = {k: [] for k in variants}
    profiles = {}
    for rep in range(args.reps):
        order = list(variants) if rep % 2 == 0 else list(reversed(variants))
        for name in order:
            seconds, profiles[name] = _fit(results, variants[name])
            times[name].append(seconds)
        print(f"  rep {rep + 1}: " + ", ".join(f"{k} {v[-1]:.1f} s" for k, v in times.items()), flush=True)
    for k, v in times.items():
        print(f"{k}: median {statistics.median(v):.1f} s, reps {' '.join(f'{x:.1f}' for x in v)}")
    ratios = [b / a for a, b in zip(times["batch (HEAD)"], times["one by one"])]
    print(f"one by one takes {statistics.median(ratios):.1f}x the batch ({min(ratios):.1f}-{max(ratios):.1f})")
    cost = candidate_cost(paper_candidate(), (224, 224))
    paths = {k: np.array(cost.path_latency_ms(p)[1:]) for k, p in profiles.items()}
    gap = np.max(np.abs(paths["batch (HEAD)"] / paths["one by one"] - 1))
    print(f"paper design's path times by the two fits: {' '.join(f'{x:.3f}' for x in paths['batch (HEAD)'])} ms "
          f"against {' '.join(f'{x:.3f}' for x in paths['one by one'])} ms (largest difference {gap:.1e})")
