"""Parameter-free operations as small named modules, so that costing sees every one of them."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class Normalize(nn.Module):
    """ImageNet mean/std, so that images enter as [0, 1] RGB everywhere (training, export, runtime)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class Resize(nn.Module):
    """Up-sampling by an integer factor (nearest in the decoder, bilinear for exit outputs).

    Bilinear is computed as two matrix products, rows then columns, with the interpolation weights of
    ``F.interpolate(..., align_corners=False)`` (``bilinear_matrix``): the same values to float
    rounding, and onnxruntime runs the products faster than its Resize kernel (each of the paper design's
    exits to 224x224), and so does PyTorch.
    ``products=False``: bilinear by interpolation (a Resize operator once exported), as the paper's graph."""

    def __init__(self, factor: int, mode: str = "nearest", products: bool = True) -> None:
        super().__init__()
        self.factor = int(factor)
        self.mode = mode
        self.products = products and mode == "bilinear"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.factor == 1:
            return x
        if self.products:
            rows = _bilinear_like(int(x.shape[-2]), self.factor, x)
            cols = _bilinear_like(int(x.shape[-1]), self.factor, x)
            return torch.matmul(torch.matmul(rows, x), cols.t())
        return F.interpolate(x, scale_factor=float(self.factor), mode=self.mode)


def _bilinear_like(n: int, factor: int, x: torch.Tensor) -> torch.Tensor:
    """``bilinear_matrix`` on ``x``'s device and dtype, copied there once: a copy from host memory to a
    GPU waits for the GPU to finish its queue, and an up-sampling in every exit would stall it so."""
    matrix = bilinear_matrix(n, factor)
    if matrix.device == x.device and matrix.dtype == x.dtype:
        return matrix
    return _bilinear_on(n, factor, x.device, x.dtype)


@lru_cache(maxsize=64)
def _bilinear_on(n: int, factor: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return bilinear_matrix(n, factor).to(device, dtype)


@lru_cache(maxsize=None)
def bilinear_matrix(n: int, factor: int) -> torch.Tensor:
    """(n * factor, n): row i holds the weights with which output i of a bilinear up-sampling of n
    values by ``factor`` mixes its inputs (pixel centres aligned as ``align_corners=False``). Built
    from plain numbers, so that an exported graph holds it as a constant."""
    src = np.maximum((np.arange(n * factor) + 0.5) / factor - 0.5, 0.0)
    low = np.minimum(np.floor(src).astype(np.int64), n - 1)
    high = np.minimum(low + 1, n - 1)
    frac = src - low
    weights = np.zeros((n * factor, n))
    rows = np.arange(n * factor)
    np.add.at(weights, (rows, low), 1.0 - frac)
    np.add.at(weights, (rows, high), frac)
    return torch.from_numpy(weights.astype(np.float32))


def one_channel_unblocked(x: torch.Tensor) -> torch.Tensor:
    """``x`` (N, 1, H, W) as it is: views in torch, a Squeeze / Unsqueeze pair in the exported graph.
    onnxruntime's blocked layout (NCHWc) does not cross that pair, so the bilinear resize after an
    exit's last convolution runs on its one channel instead of a block of 8 or 16 channels, 15 of
    them padding: an exit head (1x1 convolution then resize) runs faster so."""
    return x.squeeze(1).unsqueeze(1)


class SkipAdd(nn.Module):
    """Additive skip. Channels that only one side has pass through (no projection, no parameters),
    so decoder widths can be searched freely."""

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        cx, cs = x.shape[1], skip.shape[1]
        if cs > cx:
            skip = skip[:, :cx]
        elif cs < cx:
            skip = F.pad(skip, (0, 0, 0, 0, 0, cx - cs))
        return x + skip


class BroadcastAdd(nn.Module):
    """Adds a one-row compensation (N, C, 1, W) to every row of a feature (N, C, H, W)."""

    def forward(self, x: torch.Tensor, row: torch.Tensor) -> torch.Tensor:
        return x + row


class Concat(nn.Module):
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.cat([a, b], dim=1)


class RowGrid(nn.Module):
    """(N, C, W') column features -> (N, C + 1, H / stride, W'): every row of a coarse grid gets the
    column's feature and its own vertical position in [-1, 1] (only the image's height is read)."""

    def __init__(self, stride: int) -> None:
        super().__init__()
        self.stride = stride

    def forward(self, columns: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        n, c, w = columns.shape
        rows = image.shape[2] // self.stride
        # arange, not linspace: the ONNX exporter writes linspace's constant as float64
        position = torch.arange(rows, dtype=columns.dtype, device=columns.device) * (2.0 / max(rows - 1, 1)) - 1.0
        position = position.view(1, 1, rows, 1).expand(n, 1, rows, w)
        return torch.cat([columns.unsqueeze(2).expand(n, c, rows, w), position], dim=1)


class BandCrop(nn.Module):
    """Rows ``[row - band//2, row + band//2]`` of a feature, clamped to the feature. ``row`` is one
    row (an int), or one per feature column (an integer tensor (N, W) of the feature): a slanted scan
    line's band, gathered column by column (the same values as the slice where all rows are one)."""

    def __init__(self, band: int) -> None:
        super().__init__()
        self.band = band

    def forward(self, x: torch.Tensor, row: "int | torch.Tensor") -> torch.Tensor:
        h = x.shape[2]
        band = min(self.band, h)
        if not isinstance(row, torch.Tensor):
            top = min(max(row - band // 2, 0), h - band)
            return x[:, :, top:top + band]
        top = (row.to(x.device, torch.int64) - band // 2).clamp(0, h - band)           # (N, W)
        index = top[:, None, None, :] + torch.arange(band, device=x.device)[None, None, :, None]
        return x.gather(2, index.expand(x.shape[0], x.shape[1], band, x.shape[3]))


def conv_bn_relu(cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False),
        nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def conv1d_bn_relu(cin: int, cout: int, kernel: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv1d(cin, cout, kernel, stride, kernel // 2, bias=False),
        nn.BatchNorm1d(cout), nn.ReLU(inplace=True))
