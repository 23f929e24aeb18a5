"""The first stage of a network that works below its input size (``Candidate.downscale``): the image
averaged over ``factor`` x ``factor`` pixels, and the scan reduced to the first return of each group
of ``factor`` columns (a column without a return takes the next one's), so that every stage after it
sees a frame ``factor`` times smaller. Path 0, the scan fill and the LiDAR-only exit read the frame
as it came; the exit heads resize their depth maps back to it."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class DownscaleConfig:
    factor: int

    def build(self) -> "Downscale":
        return Downscale(self)


class FirstReturns(nn.Module):
    """(N, W) scan -> (N, W / factor): in each group of ``factor`` columns, the first with a return
    (0 where none has one)."""

    def __init__(self, factor: int) -> None:
        super().__init__()
        self.factor = factor

    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        groups = scan.reshape(scan.shape[0], scan.shape[1] // self.factor, self.factor)
        first = (groups > 0).to(torch.int64).argmax(dim=2, keepdim=True)   # argmax: the first of the maxima
        return groups.gather(2, first).squeeze(2)


class Downscale(nn.Module):
    def __init__(self, config: DownscaleConfig) -> None:
        super().__init__()
        self.pool = nn.AvgPool2d(config.factor)
        self.columns = FirstReturns(config.factor)

    def forward(self, image: torch.Tensor, scan: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.pool(image), self.columns(scan)
