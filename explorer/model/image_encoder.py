"""MobileNet v1 image encoder, truncated after N blocks, with a width multiplier."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import Normalize, conv_bn_relu
from explorer.space import MOBILENET_V1_BLOCKS, encoder_stride


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
    """MobileNet v1 blocks ``start+1 .. blocks`` (conv0 too when ``start`` is 0): the whole encoder,
    or one segment of it when encoder exits split it into several stages."""

    blocks: int
    width_mult: float
    start: int = 0

    def skip_strides(self) -> list[int]:
        """Strides of the skip features this segment emits: the feature just before each stride-2
        block it runs (the segment's own input excepted: an earlier stage already named it)."""
        strides, s = [], encoder_stride(self.start)
        for i in range(self.start, self.blocks):
            if MOBILENET_V1_BLOCKS[i][2] == 2:
                if i > self.start or self.start == 0:
                    strides.append(s)
                s *= 2
        return sorted(strides)

    def output_blocks(self) -> tuple[int, ...]:
        """For each output of the segment (its feature, then its skips by decreasing stride), how
        many encoder blocks precede it: the key into :meth:`ImageEncoder.block_features`."""
        taken = [i for i in range(self.start, self.blocks)
                 if MOBILENET_V1_BLOCKS[i][2] == 2 and (i > self.start or self.start == 0)]
        return (self.blocks, *sorted(taken, reverse=True))

    def in_channels(self) -> int:
        return 3 if self.start == 0 else scaled(MOBILENET_V1_BLOCKS[self.start - 1][1], self.width_mult)

    def out_channels(self) -> int:
        return scaled(MOBILENET_V1_BLOCKS[self.blocks - 1][1], self.width_mult)

    def build(self) -> "ImageEncoder":
        return ImageEncoder(self)


class ImageEncoder(nn.Module):
    """Returns the segment's output feature and one skip feature per stride it leaves (the last
    block's output at that resolution), in order of decreasing stride."""

    def __init__(self, config: ImageEncoderConfig) -> None:
        super().__init__()
        self.config = config
        wm = config.width_mult
        if config.start == 0:
            self.normalize = Normalize()
            self.conv0 = conv_bn_relu(3, scaled(32, wm), 3, 2)
        self.blocks = nn.ModuleList(
            DepthwiseSeparable(scaled(cin, wm), scaled(cout, wm), s)
            for cin, cout, s in MOBILENET_V1_BLOCKS[config.start:config.blocks])

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        start = self.config.start
        if start == 0:
            x = self.conv0(self.normalize(x))
        stride = encoder_stride(start)
        skips = {}
        for i, block in zip(range(start, self.config.blocks), self.blocks):
            if MOBILENET_V1_BLOCKS[i][2] == 2:
                if i > start or start == 0:
                    skips[stride] = x
                stride *= 2
            x = block(x)
        return (x, *(skips[s] for s in sorted(skips, reverse=True)))

    def block_features(self, x: torch.Tensor, keep: set[int]) -> dict[int, torch.Tensor]:
        """The whole encoder's feature after each number of blocks in ``keep`` (0 = after conv0):
        every output of every segment of this width is one of these (``output_blocks``)."""
        if self.config.start != 0:
            raise ValueError("block features are taken from a whole encoder (start 0)")
        x = self.conv0(self.normalize(x))
        features = {0: x} if 0 in keep else {}
        for i, block in enumerate(self.blocks, start=1):
            x = block(x)
            if i in keep:
                features[i] = x
        return features
