"""The network family of DESIGN.md: image encoder, LiDAR encoder, ECU, decoder, exits."""

from explorer.model.exits import interpolate_scan
from explorer.model.network import AnytimeDepthNet, StageSpec, build_network, stage_specs

__all__ = ["AnytimeDepthNet", "StageSpec", "build_network", "interpolate_scan", "stage_specs"]
