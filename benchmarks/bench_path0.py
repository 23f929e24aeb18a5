"""Path 0 as a stage (``scan_fill``, what residual exits correct): each column's nearest return found in
a few passes over the columns (``explorer.model.exits.interpolate_scan``) against a search of a W x W
matrix of column distances, in onnxruntime (the graph the runtime runs) and in PyTorch, at the widths
of the three calibration sizes. The passes exist because the search's cost grows with W squared; the
ratio per repetition says what they save.

    python benchmarks/bench_path0.py [--reps 5]

Every size's four variants are timed in interleaved blocks in each repetition; the two fills must
give the same maps.
"""

import io

import numpy as np
import torch

from explorer.calibration.measure import session
from explorer.model.exits import interpolate_scan

from harness import Bench, time_interleaved

SIZES = ((224, 224), (224, 320), (192, 640))


def _by_search(scan: torch.Tensor, height: int) -> torch.Tensor:
    """The search the passes replace: distances to every column, missing ones pushed away, argmin."""
    n, w = scan.shape
    cols = torch.arange(w, dtype=scan.dtype)
    distance = (cols[:, None] - cols[None, :]).abs()
    invalid = (scan <= 0).to(scan.dtype) * (4.0 * w)
    nearest = (distance[None] + invalid[:, None, :]).argmin(dim=2)
    return torch.gather(scan, 1, nearest)[:, None, None, :].expand(n, 1, height, w)


class _Path0(torch.nn.Module):
    def __init__(self, fill, height: int) -> None:
        super().__init__()
        self.fill, self.height = fill, height

    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        return self.fill(scan, self.height)


def _graph(fill, height: int, width: int) -> bytes:
    buf = io.BytesIO()
    torch.onnx.export(_Path0(fill, height), (torch.rand(1, width),), buf, opset_version=17, dynamo=False,
                      input_names=["scan"])
    return buf.getvalue()


def _variants(h: int, w: int, rng) -> dict:
    """{variant: call} for one size; raises if the two fills disagree."""
    scan = rng.uniform(0.5, 10.0, (1, w)).astype(np.float32)
    scan[rng.random((1, w)) < 0.5] = 0.0   # half the columns without a return
    t = torch.from_numpy(scan)
    fills = {"search": _by_search, "passes": interpolate_scan}
    sessions = {k: session(_graph(f, h, w)) for k, f in fills.items()}
    if not np.array_equal(*(s.run(None, {"scan": scan})[0] for s in sessions.values())):
        raise SystemExit(f"{h}x{w}: the search and the passes give different maps")
    return {**{f"ort_{k}": (lambda s=s: s.run(None, {"scan": scan})) for k, s in sessions.items()},
            **{f"torch_{k}": (lambda f=f: f(t, h)) for k, f in fills.items()}}


if __name__ == "__main__":
    bench = Bench(__file__, "Path 0 (nearest return per column): passes against a distance-matrix search", __doc__,
                  reps=5)
    args = bench.parse_args(bench.parser())
    rng = np.random.default_rng(0)
    cases = {f"{h}x{w}": _variants(h, w, rng) for h, w in SIZES}
    for size in cases:
        for runtime, name in (("ort", "onnxruntime"), ("torch", "PyTorch")):
            for fill in ("passes", "search"):
                bench.figure(f"{runtime}_{fill}_us_{size}", f"{name} {fill} at {size}", "us", "lower")
            bench.figure(f"{runtime}_search_over_passes_{size}", f"{name} search / passes at {size}", "x", "higher")
    for rep in bench.repetitions():
        for size, fns in cases.items():
            ms = time_interleaved(fns, rep, blocks=10, per_block=20)
            for runtime in ("ort", "torch"):
                bench.add(f"{runtime}_passes_us_{size}", 1000 * ms[f"{runtime}_passes"])
                bench.add(f"{runtime}_search_us_{size}", 1000 * ms[f"{runtime}_search"])
                bench.add(f"{runtime}_search_over_passes_{size}", ms[f"{runtime}_search"] / ms[f"{runtime}_passes"])
    bench.finish()
