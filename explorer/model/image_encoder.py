"""MobileNet v1 image encoder, truncated after N blocks, with a width multiplier."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import Normalize, conv_bn_relu
from explorer.space import MOBILENET_V1_BLOCKS


def scaled(channels: int, width_mult: float) -> int:
    """Channels times the width multiplier, rounded to a multiple of 8 (MobileNet's convention)."""
    return max(8, int(channels * width_mult + 4) // 8 * 8)


class DepthwiseSeparable(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.depthwise = conv_bn_relu(cin, cin, 3, stride, groups=cin)
        self.pointwise = conv_bn_relu(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pointwise(self.depthwise(x))


@dataclass(frozen=True)
class ImageEncoderConfig:
    blocks: int
    width_mult: float

    def skip_strides(self) -> list[int]:
        """Strides at which a skip feature is emitted: every stride below the output's, from 2."""
        strides, s = [2], 2
        for _, _, bs in MOBILENET_V1_BLOCKS[:self.blocks]:
            s *= bs
            strides.append(s)
        final = strides[-1]
        return sorted({x for x in strides if x < final})

    def out_channels(self) -> int:
        return scaled(MOBILENET_V1_BLOCKS[self.blocks - 1][1], self.width_mult)

    def build(self) -> "ImageEncoder":
        return ImageEncoder(self)


class ImageEncoder(nn.Module):
    """Returns the stride-S feature and one skip feature per lower stride (the last block's output
    at that resolution), in order of decreasing stride."""

    def __init__(self, config: ImageEncoderConfig) -> None:
        super().__init__()
        self.config = config
        wm = config.width_mult
        self.normalize = Normalize()
        self.conv0 = conv_bn_relu(3, scaled(32, wm), 3, 2)
        self.blocks = nn.ModuleList(
            DepthwiseSeparable(scaled(cin, wm), scaled(cout, wm), s)
            for cin, cout, s in MOBILENET_V1_BLOCKS[:config.blocks])
        self.skip_strides = config.skip_strides()

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        x = self.conv0(self.normalize(image))
        stride, skips = 2, {}
        for block, (_, _, s) in zip(self.blocks, MOBILENET_V1_BLOCKS):
            if s == 2:
                skips[stride] = x
                stride *= 2
            x = block(x)
        return (x, *(skips[s] for s in sorted(self.skip_strides, reverse=True)))
