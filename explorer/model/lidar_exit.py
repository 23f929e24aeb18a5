"""The LiDAR-only path: a tiny network that turns the scan into a full depth map before any image
stage runs. The scan is encoded by strided 1D convs, spread over a coarse grid of rows with each
row's vertical position, and two pointwise convs give depth per cell (the relation between a
column's scan depth and the depth above and below it is what they learn: walls, floor, ceiling)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.exits import DEPTH_INIT_M
from explorer.model.lidar_encoder import SCAN_SCALE_M
from explorer.model.ops import Resize, RowGrid, SkipAdd, conv1d_bn_relu, conv_bn_relu, one_channel_unblocked

#: The grid the LiDAR-only path predicts on, relative to the image (then resized bilinearly).
LIDAR_EXIT_STRIDE = 8
LIDAR_EXIT_WIDTH = 16


@dataclass(frozen=True)
class LidarExitConfig:
    width: int = LIDAR_EXIT_WIDTH
    stride: int = LIDAR_EXIT_STRIDE
    residual: bool = False      # the output corrects path 0 (a third input) instead of replacing it

    def build(self) -> "LidarExit":
        return LidarExit(self)


class LidarExit(nn.Module):
    def __init__(self, config: LidarExitConfig) -> None:
        super().__init__()
        w, strided = config.width, config.stride.bit_length() - 1
        self.columns = nn.Sequential(*(conv1d_bn_relu(2 if i == 0 else w, w, 3, 2) for i in range(strided)))
        self.grid = RowGrid(config.stride)
        self.cells = conv_bn_relu(w + 1, w, 1)
        self.out = nn.Conv2d(w, 1, 1)
        nn.init.constant_(self.out.bias, 0.0 if config.residual else DEPTH_INIT_M)
        self.resize = Resize(config.stride, "bilinear")
        if config.residual:
            self.correct = SkipAdd()

    def forward(self, scan: torch.Tensor, image: torch.Tensor, path_0: torch.Tensor | None = None) -> torch.Tensor:
        x = torch.stack([scan / SCAN_SCALE_M, (scan > 0).to(scan.dtype)], dim=1)
        depth = self.resize(one_channel_unblocked(self.out(self.cells(self.grid(self.columns(x), image)))))
        return depth if path_0 is None else self.correct(depth, path_0)
