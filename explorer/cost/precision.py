"""What int8 costing needs to know of an int8 export: which workloads run quantized, which stages stay
fp32, and when a stage is kept int8. The exporter (``explorer.deploy.quantize``) follows the same data,
so the cost model prices what the export builds."""

from __future__ import annotations

#: an export keeps a stage int8 where it takes at most this fraction of its fp32 time (timing noise
#: would otherwise flip stages that int8 leaves as fast as they were)
INT8_KEEP_RATIO = 0.95

#: Workload kinds an int8 stage graph runs quantized: every convolution (the rest, resizes and
#: additions, are quantized too, and priced by the int8 profile's fit of whole stage graphs).
QUANTIZABLE_KINDS = ("pointwise", "pointwise_1ch", "conv", "conv1d", "deconv", "depthwise")

#: Stages an int8 graph keeps fp32 around them. The LiDAR encoder reads the scan's metric depths, which
#: every path's scale rests on, and is 1-D and cheap: quantizing it cost the paper design several percent
#: of RMSE on its last path, and keeping it fp32 cost no time. Keeping the fusion unit or the exit head
#: fp32 instead did not help.
FLOAT_STAGES = ("lidar_encoder",)


def workload_quantized(w) -> bool:
    """Whether an int8 stage graph runs the cost-model ``Workload`` ``w`` as a quantized convolution
    (what the calibration times in int8 alone, besides whole graphs)."""
    return w.kind in QUANTIZABLE_KINDS and w.stage not in FLOAT_STAGES
