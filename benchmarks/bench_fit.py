"""The host fit (``fit_results``: every layer and stage graph a calibration timed, fp32 and int8, the
body exponent's grid) with the observations priced as one batch of arrays
(``explorer.cost.fit.ObservationBatch``) against one Python call per workload, on the same
measurements: how long a fit takes, since calibration and the study refit often, and how far the two
fitted profiles' predictions for the paper design lie apart (they should agree to rounding).

    python benchmarks/bench_fit.py [--calibration results.json] [--reps 3]

Without ``--calibration`` (a calibration's probe results) it first calibrates this machine quickly
(``explorer calibrate --quick``'s sweep, a few minutes) for measurements to fit. The two pricings
alternate within each repetition.
"""

import tempfile
import time
from pathlib import Path

import numpy as np

import explorer.cost.fit as fit
from explorer.calibration.calibrate import calibrate, fit_results, read_results
from explorer.cost import candidate_cost
from explorer.space import paper_candidate

from harness import Bench, interleave


class _OneByOne:
    """The reference pricing: ``predict_ms`` for each observation, ``layer_ms`` for each workload."""

    def __init__(self, observations) -> None:
        self.observations = list(observations)

    def predict_ms(self, profile) -> np.ndarray:
        return np.array([fit.predict_ms(profile, o) for o in self.observations])


def _fit(results: dict, batch: type) -> tuple[float, object]:
    """(seconds, profile) of ``fit_results`` with ``batch`` as the module's ObservationBatch."""
    kept, fit.ObservationBatch = fit.ObservationBatch, batch
    try:
        t0 = time.perf_counter()
        prof = fit_results(results)
        return time.perf_counter() - t0, prof
    finally:
        fit.ObservationBatch = kept


if __name__ == "__main__":
    bench = Bench(__file__, "Host fit: observations priced as one batch against one by one", __doc__)
    ap = bench.parser()
    ap.add_argument("--calibration", type=Path,
                    help="a calibration's probe results (bench_devices.py --save keeps them)")
    args = bench.parse_args(ap)
    with tempfile.TemporaryDirectory() as tmp:
        path = args.calibration
        if path is None:
            path = Path(tmp) / "calibration.json"
            print("calibrating this machine (quick sweep) for measurements to fit ...", flush=True)
            calibrate(scale=0.35, repeats=5, energy=False, results_out=path)
        results = read_results(path)
    bench.note(f"measurements from {'a quick calibration' if args.calibration is None else args.calibration}")
    bench.figure("batch_s", "fit, observations priced as one batch", "s", "lower")
    bench.figure("one_by_one_s", "fit, observations priced one by one", "s", "lower")
    bench.figure("one_by_one_over_batch", "one by one / batch", "x", "higher")
    bench.figure("path_gap", "largest relative difference of the paper design's path times", "", "lower")
    cost = candidate_cost(paper_candidate(), (224, 224))
    for rep in bench.repetitions():
        got = interleave({"batch": lambda: _fit(results, fit.ObservationBatch),
                          "one_by_one": lambda: _fit(results, _OneByOne)}, rep)
        bench.add("batch_s", got["batch"][0])
        bench.add("one_by_one_s", got["one_by_one"][0])
        bench.add("one_by_one_over_batch", got["one_by_one"][0] / got["batch"][0])
        paths = {k: np.array(cost.path_latency_ms(prof)[1:]) for k, (_, prof) in got.items()}
        bench.add("path_gap", float(np.max(np.abs(paths["batch"] / paths["one_by_one"] - 1))))
    bench.finish()
