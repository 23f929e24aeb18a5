"""Depth metrics as FastDepth and sparse-to-dense compute them: over pixels with target > 0, per
image, in metres; RMSE, MAE, REL (mean |pred - gt| / gt), delta_k (max(p/g, g/p) < 1.25^k)."""

from __future__ import annotations

import numpy as np
import torch

METRICS = ("rmse", "mae", "rel", "delta1", "delta2", "delta3")


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
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64).reshape(-1)


def batch_depth_metrics(pred: torch.Tensor, target: torch.Tensor) -> list[dict[str, float]]:
    """:func:`depth_metrics` of every image of a batch (N, ...), computed at once."""
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
    """Averages per-image metrics (the convention of FastDepth's evaluation)."""

    def __init__(self) -> None:
        self.sums = {m: 0.0 for m in METRICS}
        self.count = 0

    def add(self, metrics: dict[str, float]) -> None:
        if any(np.isnan(v) for v in metrics.values()):
            return
        for m in METRICS:
            self.sums[m] += metrics[m]
        self.count += 1

    def result(self) -> dict[str, float]:
        return {m: (self.sums[m] / self.count if self.count else float("nan")) for m in METRICS}
