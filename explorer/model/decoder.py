"""FastDepth-style decoder stage: depthwise 5x5, pointwise 1x1, nearest x2, additive skip."""

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

    def build(self) -> "DecoderStage":
        return DecoderStage(self)


class DecoderStage(nn.Module):
    def __init__(self, config: DecoderStageConfig) -> None:
        super().__init__()
        self.depthwise = conv_bn_relu(config.in_channels, config.in_channels, 5, groups=config.in_channels)
        self.pointwise = conv_bn_relu(config.in_channels, config.out_channels, 1)
        self.upsample = Resize(2, "nearest")
        self.skip = SkipAdd() if config.has_skip else None

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        x = self.upsample(self.pointwise(self.depthwise(x)))
        return self.skip(x, skip) if self.skip is not None else x
