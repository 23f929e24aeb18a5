"""Workloads: every layer of every stage with its kind, shapes, MACs, parameters and bytes moved.

They are read off the real torch modules (one model definition): each stage is built once on the
meta device (no memory, no compute) and traced with forward hooks; the result is cached by the
stage's config and input shapes, so costing a whole space builds each distinct stage only once.
BatchNorm and ReLU are folded into the preceding convolution, as every deployment runtime does:
their parameters are added to that layer, they add no MACs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Hashable

import torch
from torch import nn

from explorer.errors import UserError
from explorer.model import ops
from explorer.model.downscale import FirstReturns
from explorer.model.exits import ScanFill
from explorer.model.network import StageSpec, stage_specs
from explorer.model.reference import get_reference
from explorer.space import Candidate

BYTES_PER_VALUE = 4  # float32

#: Layer kinds a device profile must price.
KINDS = ("conv", "pointwise", "depthwise", "conv1d", "resize", "add", "concat", "slice")
#: Layer kinds a profile may price; one that does not prices them as the kind named here (so
#: profiles written before the kind existed still load). Transposed convolutions only occur in the
#: reference networks (sparse-to-dense's decoder), and TVM's are slow enough to need their own rate.
#: A 1x1 convolution to one channel (every exit head's last layer) is a matrix-vector product:
#: memory-bound where other pointwise layers are not (on a CPU, several times slower than the
#: pointwise rate says at full resolution), so it has its own kind.
#: Bilinear up-sampling as two matrix products (``ops.Resize``, an exit's last step) is one more:
#: a profile that does not price it prices it as the matrix products of pointwise layers.
OPTIONAL_KINDS = {"deconv": "conv", "pointwise_1ch": "pointwise", "bilinear": "pointwise"}
ALL_KINDS = KINDS + tuple(OPTIONAL_KINDS)


@dataclass(frozen=True)
class Workload:
    stage: str
    layer: str
    kind: str
    in_shape: tuple[int, ...]
    out_shape: tuple[int, ...]
    kernel: int
    stride: int
    macs: int
    params: int
    bytes_read: int
    bytes_written: int

    def as_dict(self) -> dict:
        d = asdict(self)
        d["in_shape"] = "x".join(map(str, self.in_shape))
        d["out_shape"] = "x".join(map(str, self.out_shape))
        return d


def _conv_kind(m: nn.Module) -> str:
    if isinstance(m, nn.Conv1d):
        return "conv1d"
    if m.groups > 1 and m.groups == m.in_channels:
        return "depthwise"
    if all(k == 1 for k in m.kernel_size):
        return "pointwise_1ch" if m.out_channels == 1 else "pointwise"
    return "conv"


def _numel(shape: tuple[int, ...]) -> int:
    return math.prod(shape)


def bilinear_products(stage: str, layer: str, in_shape: tuple[int, int, int], factor: int) -> Workload:
    """A bilinear up-sampling by ``factor`` as ``ops.Resize`` computes it: two matrix products, rows then
    columns. Each output row mixes every input row, then each output value every column of its row
    (most weights 0, all multiplied); the interpolation matrices (constants, not parameters) are
    read, the rows-first product written and read again."""
    c, hi, wi = in_shape
    ho, wo = hi * factor, wi * factor
    between = c * ho * wi
    return Workload(stage, layer, "bilinear", tuple(in_shape), (c, ho, wo), 0, factor,
                    c * (ho * hi * wi + ho * wi * wo), 0,
                    (c * hi * wi + ho * hi + wo * wi + between) * BYTES_PER_VALUE, (c * ho * wo + between) * BYTES_PER_VALUE)


def _same_shape(x: torch.Tensor) -> torch.Tensor:
    return x


def _run_with_hooks(module: nn.Module, hook, inputs: list):
    """``module``'s output on ``inputs``, ``hook(name)`` called after each leaf (and each Resize and
    SkipAdd); the module is left as it was."""
    handles, norms = [], []
    for name, m in module.named_modules():
        if not list(m.children()) or isinstance(m, (ops.Resize, ops.SkipAdd)):
            handles.append(m.register_forward_hook(hook(name)))
        if isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
            # a BatchNorm keeps its input's shape and is folded (the hook reads its parameters only); on
            # meta tensors PyTorch runs its Python decomposition, most of the time of tracing a stage
            m.forward = _same_shape
            norms.append(m)
    try:
        with torch.no_grad():
            return module(*inputs)
    finally:
        for h in handles:
            h.remove()
        for m in norms:
            del m.forward


def trace_stage(module: nn.Module, stage: str, inputs: list) -> tuple[list[Workload], list[tuple[int, ...]]]:
    """Run ``module`` on meta tensors of the given shapes (ints pass through) and record layers."""
    records: list[Workload] = []

    def hook(name: str):
        def fn(m: nn.Module, args: tuple, out) -> None:
            tensors = [a for a in args if isinstance(a, torch.Tensor)]
            in_shape = tuple(tensors[0].shape[1:])
            out_shape = tuple(out.shape[1:])
            n_in = sum(_numel(tuple(t.shape[1:])) for t in tensors)
            n_out = _numel(out_shape)
            params = sum(p.numel() for p in m.parameters(recurse=False))
            if isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
                if records:
                    r = records[-1]
                    records[-1] = Workload(**{**asdict(r), "params": r.params + params})
                return
            if isinstance(m, (nn.Conv1d, nn.Conv2d)):
                kernel = math.prod(m.kernel_size)
                macs = n_out * (m.in_channels // m.groups) * kernel
                kind, k, s = _conv_kind(m), m.kernel_size[0], m.stride[0]
            elif isinstance(m, nn.ConvTranspose2d):
                # each input value meets every weight of its group once
                kernel = math.prod(m.kernel_size)
                macs = n_in * (m.out_channels // m.groups) * kernel
                kind, k, s = "deconv", m.kernel_size[0], m.stride[0]
            elif isinstance(m, ops.Resize) and m.products and in_shape != out_shape:
                records.append(bilinear_products(stage, name, in_shape, m.factor))
                return
            elif isinstance(m, (ops.Resize, nn.Upsample)):
                if in_shape == out_shape:
                    return
                # bilinear: 4 multiply-adds per output value; nearest only copies
                kind, k = "resize", 0
                s = max(1, round(out_shape[-1] / in_shape[-1]))
                macs = 4 * n_out if m.mode == "bilinear" else 0
            elif isinstance(m, (nn.MaxPool2d, nn.AvgPool2d)):
                # a window max or mean: memory-bound resampling, priced like a resize by the bytes it moves
                kind, k, s, macs = "resize", 0, int(m.stride if isinstance(m.stride, int) else m.stride[0]), 0
            elif isinstance(m, FirstReturns):
                kind, k, s, macs = "slice", 0, m.factor, 0
            elif isinstance(m, (ops.SkipAdd, ops.BroadcastAdd, ops.Normalize)):
                kind, k, s, macs = "add", 0, 1, 0
            elif isinstance(m, ops.Concat):
                kind, k, s, macs = "concat", 0, 1, 0
            elif isinstance(m, ops.RowGrid):
                kind, k, s, macs = "concat", 0, 1, 0
                n_in = n_out  # the image is read for its height only
            elif isinstance(m, ScanFill):
                # each column's nearest return: a dozen element-wise passes over the W columns (counts,
                # positions, the nearest on either side; ``interpolate_scan``)
                w = in_shape[-1]
                records.append(Workload(stage, f"{name}.nearest", "add", (w,), (w,), 0, 1, 0, 0,
                                        8 * w * BYTES_PER_VALUE, 4 * w * BYTES_PER_VALUE))
                # path 0 as a tensor: each column copies its nearest return down the image
                kind, k, s, macs = "resize", 0, 1, 0
                n_in = _numel(in_shape)  # the image is read for its height only
            elif isinstance(m, ops.BandCrop):
                kind, k, s, macs = "slice", 0, 1, 0
                n_in = n_out  # reads only the band
            else:
                return  # ReLU and containers: folded or structural
            records.append(Workload(stage, name, kind, in_shape, out_shape, k, s, int(macs), params,
                                    (n_in + params) * BYTES_PER_VALUE, n_out * BYTES_PER_VALUE))
        return fn

    out = _run_with_hooks(module, hook, inputs)
    outs = out if isinstance(out, tuple) else (out,)
    return records, [tuple(o.shape) for o in outs]


@lru_cache(maxsize=8192)
def stage_cost(config: Hashable, name: str, in_shapes: tuple, scan_row: int | None):
    with torch.device("meta"):
        module = config.build().eval()
        inputs: list = [torch.empty(s) for s in in_shapes]
    if scan_row is not None:
        inputs.append(scan_row)
    records, out_shapes = trace_stage(module, name, inputs)
    return tuple(records), tuple(out_shapes)


def candidate_workloads(candidate: Candidate, input_size: tuple[int, int] = (224, 224),
                        specs: list[StageSpec] | None = None) -> list[Workload]:
    """All workloads of ``candidate`` at ``input_size`` (H, W), batch 1, in execution order."""
    h, w = input_size
    if h % candidate.stride or w % candidate.stride:
        raise UserError(f"input {h}x{w} does not divide by the encoder stride {candidate.stride}: "
                        f"use sides that are multiples of {candidate.stride}")
    shapes: dict[str, tuple] = {"image": (1, 3, h, w), "scan": (1, w)}
    out: list[Workload] = []
    for spec in specs or stage_specs(candidate):
        in_shapes = tuple(shapes[n] for n in spec.inputs)
        records, out_shapes = stage_cost(spec.config, spec.name, in_shapes,
                                          h // 2 if spec.uses_scan_row else None)
        shapes.update(zip(spec.outputs, out_shapes))
        out.extend(records)
    return out


@lru_cache(maxsize=64)
def reference_workloads(name: str, input_size: tuple[int, int] = (224, 224)) -> tuple[Workload, ...]:
    """All workloads of the reference network ``name`` (``explorer.model.reference``) at
    ``input_size`` (H, W), batch 1, as one stage called 'network'."""
    ref = get_reference(name)
    h, w = input_size
    if min(h, w) < ref.stride:   # padding carries even a 1x1 image through every layer: no depth map
        raise UserError(f"{name} cannot run at {h}x{w}: each side must be at least {ref.stride} pixels")
    with torch.device("meta"):
        module = ref.build().eval()
        image = torch.empty(ref.input_shape(tuple(input_size)))
    try:
        records, _ = trace_stage(module, "network", [image])
    except RuntimeError:  # skips or concatenations whose sizes do not meet
        h, w = input_size
        raise UserError(f"{name} cannot run at {h}x{w}: its skips need sides that are multiples of "
                        f"{ref.stride}") from None
    return tuple(records)


def dilated_count_macs(workloads: tuple[Workload, ...] | list[Workload]) -> int:
    """Multiply-adds as FLOP counters such as thop count them: a transposed convolution as the
    convolution over its zero-dilated input that it is computed as (every output value x input
    channels x kernel), 4x its real multiply-adds for a 2x2 stride-2 layer. The paper's GFLOPs for
    sparse-to-dense follow this convention; every other layer counts as it is."""
    total = 0
    for w in workloads:
        if w.kind == "deconv":
            total += math.prod(w.out_shape) * w.in_shape[0] * w.kernel ** 2
        else:
            total += w.macs
    return total
