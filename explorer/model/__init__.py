"""The network family of the design guide (in docs/): image encoder, LiDAR encoder, ECU, decoder, exits."""

from explorer.model.exits import interpolate_scan
from explorer.model.network import (
    AnytimeDepthNet,
    StageSpec,
    build_network,
    stage_specs,
)
from explorer.model.reference import ReferenceDepthNet, ReferenceModel

__all__ = ["AnytimeDepthNet", "StageSpec", "build_model", "build_network", "interpolate_scan", "stage_specs"]


def build_model(model):
    """The network for a candidate (:func:`build_network`) or for a reference network's
    :class:`~explorer.model.reference.ReferenceModel` (a two-path ``ReferenceDepthNet``)."""
    return ReferenceDepthNet(model.name) if isinstance(model, ReferenceModel) else build_network(model)
