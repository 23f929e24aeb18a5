"""Depth metrics as FastDepth and sparse-to-dense compute them: over pixels with target > 0, per
image, in metres; RMSE, MAE, REL (mean |pred - gt| / gt), delta_k (max(p/g, g/p) < 1.25^k)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:   # the runtime install scores its maps with NumPy alone: no torch there
    import torch

METRICS = ("rmse", "mae", "rel", "delta1", "delta2", "delta3")
#: the score of a path where the frames have no depth: see explorer.training.selfsup.photometric_score
PHOTOMETRIC = "photometric"


def depth_metrics(pred: torch.Tensor | np.ndarray, target: torch.Tensor | np.ndarray) -> dict[str, float]:
    """Metrics of one image (any shape; pred and target the same size). Computed with NumPy: the
    runtime scores its maps between runs (``runtime.measured_anytime``), and a PyTorch operation there
    leaves PyTorch's OpenMP threads spinning for milliseconds on the cores onnxruntime's next run needs
    (the paper design's runs with a 9 ms deadline reached path 4 in 0 of 20 instead of 20 of 20 here)."""
    p = _float64(pred)
    t = _float64(target)
    if p.shape != t.shape:
        raise ValueError(f"prediction has {p.size} values but target {t.size}")
    valid = t > 0
    if not valid.any():
        return {m: float("nan") for m in METRICS}
    p, t = p[valid], t[valid]
    err = np.abs(p - t)
    # ratios with a non-positive prediction count as failures, as a 0 prediction would
    ratio = np.maximum(p / t, t / np.maximum(p, 1e-9))
    return {
        "rmse": float(np.sqrt(np.mean(err ** 2))),
        "mae": float(np.mean(err)),
        "rel": float(np.mean(err / t)),
        "delta1": float(np.mean(ratio < 1.25)),
        "delta2": float(np.mean(ratio < 1.25 ** 2)),
        "delta3": float(np.mean(ratio < 1.25 ** 3)),
    }


def _float64(x: torch.Tensor | np.ndarray) -> np.ndarray:
    if hasattr(x, "detach"):   # a torch.Tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64).reshape(-1)


def batch_depth_metrics(pred: torch.Tensor, target: torch.Tensor) -> list[dict[str, float]]:
    """:func:`depth_metrics` of every image of a batch (N, ...), computed at once."""
    import torch
    p, t = pred.double().flatten(1), target.double().flatten(1)
    if p.shape != t.shape:
        raise ValueError(f"prediction has shape {tuple(pred.shape)} but target {tuple(target.shape)}")
    valid = t > 0
    n = valid.sum(1).double()
    safe_t = torch.where(valid, t, torch.ones_like(t))
    err = torch.where(valid, (p - t).abs(), torch.zeros_like(t))
    ratio = torch.maximum(p / safe_t, safe_t / p.clamp(min=1e-9))
    values = {"rmse": torch.sqrt((err ** 2).sum(1) / n), "mae": err.sum(1) / n, "rel": (err / safe_t).sum(1) / n}
    for k in (1, 2, 3):
        values[f"delta{k}"] = ((ratio < 1.25 ** k) & valid).sum(1).double() / n
    columns = {m: values[m].tolist() for m in METRICS}   # one conversion, not one per value
    return [{m: (columns[m][i] if ok else float("nan")) for m in METRICS} for i, ok in enumerate((n > 0).tolist())]


class MetricAverager:
    """Averages per-image metrics (the convention of FastDepth's evaluation), each over the images
    that have it: an image without depth has no RMSE but may have a photometric score
    (:data:`PHOTOMETRIC`)."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, metrics: dict[str, float]) -> None:
        for m, v in metrics.items():
            if not np.isnan(v):
                self.sums[m] = self.sums.get(m, 0.0) + v
                self.counts[m] = self.counts.get(m, 0) + 1

    def result(self) -> dict[str, float]:
        """Every depth metric (NaN where no image had depth), then any other metric added."""
        names = list(METRICS) + [m for m in self.sums if m not in METRICS]
        return {m: (self.sums[m] / self.counts[m] if self.counts.get(m) else float("nan")) for m in names}

