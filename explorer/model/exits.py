"""Exit heads (1-2 pointwise convs to one channel, resized to full resolution) and path 0."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import BroadcastAdd, Resize

#: Initial bias of the depth output (metres): a typical indoor depth, so training starts near it.
DEPTH_INIT_M = 2.5


@dataclass(frozen=True)
class ExitHeadConfig:
    in_channels: int
    depth: int
    width: int
    upscale: int
    lidar_channels: int = 0      # > 0: the LiDAR feature at this stride is added to every row first

    def build(self) -> "ExitHead":
        return ExitHead(self)


class ExitHead(nn.Module):
    def __init__(self, config: ExitHeadConfig) -> None:
        super().__init__()
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
        nn.init.constant_(out.bias, DEPTH_INIT_M)
        layers.append(out)
        self.layers = nn.Sequential(*layers)
        self.resize = Resize(config.upscale, "bilinear")

    def forward(self, x: torch.Tensor, lidar: torch.Tensor | None = None) -> torch.Tensor:
        if lidar is not None:
            x = self.add(x, self.fuse(lidar).unsqueeze(2))
        return self.resize(self.layers(x))


def interpolate_scan(scan: torch.Tensor, height: int) -> torch.Tensor:
    """Path 0: every column takes the depth of the nearest column with a return, over all rows.

    ``scan`` is (N, W) metres with 0 for no return; the result is (N, 1, height, W). A scan with no
    return at all gives zeros.
    """
    n, w = scan.shape
    cols = torch.arange(w, device=scan.device, dtype=scan.dtype)
    distance = (cols[:, None] - cols[None, :]).abs()  # (W, W)
    invalid = (scan <= 0).to(scan.dtype) * (4.0 * w)  # (N, W): pushes missing columns away
    nearest = (distance[None] + invalid[:, None, :]).argmin(dim=2)  # (N, W)
    filled = torch.gather(scan, 1, nearest)
    return filled[:, None, None, :].expand(n, 1, height, w)
