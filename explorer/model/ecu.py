"""Error correction unit: compares the image feature near the scan line with the LiDAR feature and
adds the resulting compensation to every row of the image feature."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from explorer.model.ops import BandCrop, BroadcastAdd, Concat


@dataclass(frozen=True)
class ECUConfig:
    channels: int        # image feature channels
    lidar_channels: int
    band: int
    width: int           # alignment-error channels
    stride: int          # image feature stride, to find the scan's feature row

    def build(self) -> "ECU":
        return ECU(self)


def feature_rows(scan_row: "int | torch.Tensor", stride: int) -> "int | torch.Tensor":
    """The feature row of an image row, or per feature column the row of its centre image column."""
    if not isinstance(scan_row, torch.Tensor):
        return scan_row // stride
    return torch.div(scan_row[:, stride // 2::stride], stride, rounding_mode="floor")


class ECU(nn.Module):
    def __init__(self, config: ECUConfig) -> None:
        super().__init__()
        self.stride = config.stride
        c = config.channels
        self.crop = BandCrop(config.band)
        # Summarises the band to one row: a depthwise conv spanning the band's height.
        self.summarize = nn.Conv2d(c, c, (config.band, 1), groups=c, bias=False)
        self.concat = Concat()
        self.alignment = nn.Sequential(
            nn.Conv1d(c + config.lidar_channels, config.width, 1, bias=False),
            nn.BatchNorm1d(config.width), nn.ReLU(inplace=True))
        self.compensation = nn.Conv1d(config.width, c, 1)
        self.add = BroadcastAdd()
        self.band = config.band

    def forward(self, feature: torch.Tensor, lidar: torch.Tensor, scan_row: "int | torch.Tensor") -> torch.Tensor:
        """``scan_row``: the image row of the scan, or each image column's (an integer tensor (N, W)),
        whose band is then cropped around each feature column's own row."""
        band = self.crop(feature, feature_rows(scan_row, self.stride))
        if band.shape[2] < self.band:  # feature shorter than the band: pad rows to the kernel
            band = nn.functional.pad(band, (0, 0, 0, self.band - band.shape[2]))
        summary = self.summarize(band).squeeze(2)
        error = self.alignment(self.concat(summary, lidar))
        return self.add(feature, self.compensation(error).unsqueeze(2))
