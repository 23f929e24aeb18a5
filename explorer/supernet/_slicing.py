"""Where each tensor of a candidate's network lives in the supernet, and which slice of it it is.

A candidate's stage modules are built from the same configs as the supernet's (one model
definition); a tensor of the candidate is the leading slice of the supernet tensor it maps to
(first channels, first blocks, first layers, Once-for-All style), with two exceptions: the ECU's
alignment conv reads a concatenation [image summary | LiDAR feature], so its input channels are the
first ones of each part, and the ECU's band summary keeps the centre rows of the widest kernel.
"""

from __future__ import annotations

import torch

from explorer.model.decoder import DecoderStageConfig
from explorer.model.downscale import DownscaleConfig
from explorer.model.ecu import ECUConfig
from explorer.model.exits import ExitHeadConfig, ScanFillConfig
from explorer.model.image_encoder import ImageEncoderConfig
from explorer.model.lidar_encoder import LidarEncoderConfig
from explorer.model.lidar_exit import LidarExitConfig
from explorer.model.network import StageSpec


def slot_of(spec: StageSpec) -> str:
    """The supernet module that holds ``spec``'s weights."""
    cfg = spec.config
    if isinstance(cfg, ImageEncoderConfig):
        return "image_encoder"
    if isinstance(cfg, LidarEncoderConfig):
        return "lidar_encoder"
    if isinstance(cfg, ECUConfig):
        return "ecu"
    if isinstance(cfg, (ScanFillConfig, DownscaleConfig)):
        return spec.name
    # a head that corrects the scan learns another output than one that replaces it: its own weights
    if isinstance(cfg, LidarExitConfig):
        return "lidar_exit" + ("_r" if cfg.residual else "")
    if isinstance(cfg, DecoderStageConfig):
        return spec.name
    if isinstance(cfg, ExitHeadConfig):
        return f"{spec.name}_d{cfg.depth}" + ("_r" if cfg.residual else "")
    raise TypeError(f"no supernet slot for stage {spec.name} ({type(cfg).__name__})")


def super_name(spec: StageSpec, local: str) -> str:
    """The supernet tensor name of tensor ``local`` of ``spec``'s module."""
    cfg = spec.config
    if isinstance(cfg, ImageEncoderConfig) and local.startswith("blocks."):
        _, j, rest = local.split(".", 2)
        local = f"blocks.{cfg.start + int(j)}.{rest}"
    return f"{slot_of(spec)}.{local}"


def slice_of(spec: StageSpec, local: str, full: torch.Tensor, shape: torch.Size, wide_ecu_channels: int = 0
             ) -> torch.Tensor:
    """The part of supernet tensor ``full`` that is ``spec``'s tensor ``local`` (of ``shape``):
    a view where it can be (so gradients and BatchNorm statistics reach the supernet).
    ``wide_ecu_channels`` is the image-feature width of the supernet's ECU."""
    if full.dim() == 0:
        return full
    if len(shape) != full.dim() or any(s > f for s, f in zip(shape, full.shape)):
        raise ValueError(f"{spec.name}.{local}: {tuple(shape)} is not a slice of {tuple(full.shape)}")
    cfg = spec.config
    if isinstance(cfg, ECUConfig) and local == "alignment.0.weight":
        c, lidar, wide = cfg.channels, cfg.lidar_channels, wide_ecu_channels
        return torch.cat([full[:shape[0], :c], full[:shape[0], wide:wide + lidar]], dim=1)
    if isinstance(cfg, ECUConfig) and local == "summarize.weight":
        top = (full.shape[2] - shape[2]) // 2
        return full[:shape[0], :, top:top + shape[2]]
    return full[tuple(slice(0, n) for n in shape)]

