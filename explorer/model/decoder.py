"""FastDepth-style decoder stage: depthwise 5x5, pointwise 1x1, nearest x2, additive skip.

The last stage, when it has no skip, leaves its nearest x2 to the exit head that reads it
(``upsample=False``): the head's 1x1 convolutions (and BatchNorm, ReLU) act on each pixel alone and
commute with nearest up-sampling, so they run on a quarter of the pixels and the head up-samples
its one output channel instead of the stage's every channel: the same values."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import Resize, SkipAdd, conv_bn_relu


@dataclass(frozen=True)
class DecoderStageConfig:
    in_channels: int
    out_channels: int
    has_skip: bool
    upsample: bool = True    # False: the exit head reading this stage up-samples (see the module doc)

    def build(self) -> "DecoderStage":
        return DecoderStage(self)


class DecoderStage(nn.Module):
    def __init__(self, config: DecoderStageConfig) -> None:
        super().__init__()
        self.depthwise = conv_bn_relu(config.in_channels, config.in_channels, 5, groups=config.in_channels)
        self.pointwise = conv_bn_relu(config.in_channels, config.out_channels, 1)
        self.upsample = Resize(2 if config.upsample else 1, "nearest")
        self.skip = SkipAdd() if config.has_skip else None

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        x = self.upsample(self.pointwise(self.depthwise(x)))
        return self.skip(x, skip) if self.skip is not None else x
