"""Path 0 as a stage (``scan_fill``, what residual exits correct): each column's nearest return found in a
few passes over the columns (``explorer.model.exits.interpolate_scan``, HEAD) against the search of a
W x W matrix of column distances it replaced, in onnxruntime (the graph the runtime runs) and in
PyTorch, at the widths of the three calibration sizes. Interleaved blocks, ``--reps`` of them; every
repetition and the median.

    .venv/bin/python benchmarks/bench_path0.py [--reps 5]
"""

import argparse
import io
import statistics

import numpy as np
import torch

from explorer.calibration.measure import session
from explorer.model.exits import interpolate_scan

from _timing import time_interleaved

SIZES = ((224, 224), (224, 320), (192, 640))


def _by_search(scan: torch.Tensor, height: int) -> torch.Tensor:
    """The rule until stop 39: distances to every column, missing ones pushed away, argmin."""
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


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    for h, w in SIZES:
        scan = rng.uniform(0.5, 10.0, (1, w)).astype(np.float32)
        scan[rng.random((1, w)) < 0.5] = 0.0   # half the columns without a return
        t = torch.from_numpy(scan)
        fills = {"search": _by_search, "passes (HEAD)": interpolate_scan}
        sessions = {k: session(_graph(f, h, w)) for k, f in fills.items()}
        same = np.array_equal(*(s.run(None, {"scan": scan})[0] for s in sessions.values()))
        fns = {**{f"onnxruntime, {k}": (lambda s=s: s.run(None, {"scan": scan})) for k, s in sessions.items()},
               **{f"PyTorch, {k}": (lambda f=f: f(t, h)) for k, f in fills.items()}}
        times = {k: [] for k in fns}
        for _ in range(args.reps):
            for k, ms in time_interleaved(fns, blocks=10, per_block=20).items():
                times[k].append(ms)
        print(f"{h}x{w} (same maps: {same}):")
        for k, v in times.items():
            print(f"  {k}: median {statistics.median(v) * 1000:.1f} us, reps "
                  + " ".join(f"{x * 1000:.1f}" for x in v))
        for runtime in ("onnxruntime", "PyTorch"):
            ratios = [a / b for a, b in zip(times[f"{runtime}, search"], times[f"{runtime}, passes (HEAD)"])]
            print(f"  {runtime}: the search takes {statistics.median(ratios):.1f}x the passes "
                  f"({min(ratios):.1f}-{max(ratios):.1f})")
