"""1D convolutional encoder of the scan vector (one depth per image column, 0 = no return)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import conv1d_bn_relu

#: Scan depths are divided by this (metres) so indoor and outdoor ranges enter at a similar scale.
SCAN_SCALE_M = 10.0


@dataclass(frozen=True)
class LidarEncoderConfig:
    depth: int
    width: int
    stride: int
    taps: tuple[int, ...] = ()   # strides whose intermediate features are output too (for fusion)

    def channels(self) -> list[int]:
        strided = int(math.log2(self.stride))
        chans = [self.width * 2 ** min(i, strided - 1) for i in range(self.depth)]
        return chans

    def out_channels(self) -> int:
        return self.channels()[-1]

    def tap_channels(self, stride: int) -> int:
        """Channels of the feature at ``stride`` (after the strided layer that reaches it)."""
        return self.channels()[int(math.log2(stride)) - 1]

    def build(self) -> "LidarEncoder":
        return LidarEncoder(self)


class LidarEncoder(nn.Module):
    """Input (N, W) metres -> (N, C, W / stride): strided convs first, then stride-1 convs. With
    ``taps``, the features at those strides follow the output, in the order of ``taps``."""

    def __init__(self, config: LidarEncoderConfig) -> None:
        super().__init__()
        strided = int(math.log2(config.stride))
        layers, cin = [], 2  # channels: scaled depth, return mask
        for i, cout in enumerate(config.channels()):
            layers.append(conv1d_bn_relu(cin, cout, 3, 2 if i < strided else 1))
            cin = cout
        self.layers = nn.Sequential(*layers)
        self.tap_layers = [int(math.log2(s)) - 1 for s in config.taps]

    def forward(self, scan: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, ...]:
        x = torch.stack([scan / SCAN_SCALE_M, (scan > 0).to(scan.dtype)], dim=1)
        if not self.tap_layers:
            return self.layers(x)
        taps = {}
        for i, layer in enumerate(self.layers):
            x = layer(x)
            taps[i] = x
        return (x, *(taps[i] for i in self.tap_layers))
