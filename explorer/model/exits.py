"""Exit heads (1-2 pointwise convs to one channel, resized to full resolution) and path 0.

A residual head adds its output to path 0 (the interpolated scan, computed once per inference by the
``scan_fill`` stage): it learns a correction to the scan instead of the whole depth map, and keeps
the scan's full horizontal resolution where its own output is coarse."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import BroadcastAdd, Resize, SkipAdd, one_channel_unblocked

#: Initial bias of the depth output (metres): a typical indoor depth, so training starts near it.
DEPTH_INIT_M = 2.5


@dataclass(frozen=True)
class ExitHeadConfig:
    in_channels: int
    depth: int
    width: int
    upscale: int
    lidar_channels: int = 0      # > 0: the LiDAR feature at this stride is added to every row first
    residual: bool = False       # the output corrects path 0 (its last input) instead of replacing it
    nearest: int = 1             # > 1: the decoder stage before left its nearest up-sampling to the head
    bilinear_products: bool = True   # False: a bilinear resize operator, as the paper's graph (``ops.Resize``)

    def build(self) -> "ExitHead":
        return ExitHead(self)


class ExitHead(nn.Module):
    def __init__(self, config: ExitHeadConfig) -> None:
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        cin = config.in_channels
        if config.lidar_channels:
            self.fuse = nn.Conv1d(config.lidar_channels, cin, 1)
            self.add = BroadcastAdd()
        if config.depth == 2:
            layers += [nn.Conv2d(cin, config.width, 1, bias=False), nn.BatchNorm2d(config.width),
                       nn.ReLU(inplace=True)]
            cin = config.width
        out = nn.Conv2d(cin, 1, 1)
        nn.init.constant_(out.bias, 0.0 if config.residual else DEPTH_INIT_M)
        layers.append(out)
        self.layers = nn.Sequential(*layers)
        self.nearest = Resize(config.nearest, "nearest")
        self.resize = Resize(config.upscale, "bilinear", products=config.bilinear_products)
        if config.residual:
            self.correct = SkipAdd()

    def forward(self, x: torch.Tensor, *extra: torch.Tensor) -> torch.Tensor:
        """``extra``: the LiDAR feature when the head fuses it, then path 0 when it is residual."""
        if self.config.lidar_channels:
            x = self.add(x, self.fuse(extra[0]).unsqueeze(2))
        depth = self.layers(x)
        if self.config.nearest > 1:
            depth = self.nearest(one_channel_unblocked(depth))
        if self.config.upscale > 1:
            depth = self.resize(one_channel_unblocked(depth))
        return self.correct(depth, extra[-1]) if self.config.residual else depth


@dataclass(frozen=True)
class ScanFillConfig:
    """Path 0 as a stage, for residual exits to read (its own path stays the free fallback)."""

    def build(self) -> "ScanFill":
        return ScanFill()


class ScanFill(nn.Module):
    def forward(self, scan: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        return interpolate_scan(scan, image.shape[2])


def interpolate_scan(scan: torch.Tensor, height: int) -> torch.Tensor:
    """Path 0: every column takes the depth of the nearest column with a return, over all rows.

    ``scan`` is (N, W) metres with 0 for no return; the result is (N, 1, height, W). A scan with no
    return at all gives zeros.
    """
    n, w = scan.shape
    # In O(W), with fixed shapes (a W x W matrix of distances searched by argmin grows with W squared;
    # bench_path0 compares the two): the nearest return on the left and on the right, and
    # the closer of the two (the left one on a tie, as argmin's first minimum).
    valid = scan > 0
    cols = torch.arange(w, device=scan.device).expand(n, w)
    count = torch.cumsum(valid.to(torch.int64), dim=1)   # returns at or left of each column
    # positions[:, k]: the column of the k-th return (k from 1); slot 0 takes the columns without one
    positions = torch.zeros(n, w + 1, dtype=torch.int64, device=scan.device).scatter(
        1, torch.where(valid, count, 0), cols)
    after = count + (~valid).to(torch.int64)             # k of the first return at or right of the column
    left = positions.gather(1, count)
    right = positions.gather(1, after.clamp(max=w))
    has_left, has_right = count > 0, after <= count[:, -1:]
    take_left = has_left & (~has_right | (cols - left <= right - cols))
    nearest = torch.where(take_left, left, torch.where(has_right, right, cols))   # no return at all: itself
    filled = torch.gather(scan, 1, nearest)
    return filled[:, None, None, :].expand(n, 1, height, w)
