"""The calibration sweep: single-layer ONNX graphs of every workload kind the cost model prices, drawn
at random over channels and sizes, and the input sizes calibration candidates' stage graphs run at."""

from __future__ import annotations

import dataclasses
import random

import numpy as np
from onnx import TensorProto, helper, numpy_helper

from explorer.cost.workloads import BYTES_PER_VALUE, KINDS, Workload, bilinear_products
from explorer.model.ops import bilinear_matrix

CHANNELS = (8, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024)
SIDES = (7, 14, 28, 56, 112, 224)
MAX_MACS = 120e6
#: Input sizes of the stage graphs measured: several, so that the fit can tell per-layer costs that
#: stay from ones that grow with the tensors, and the profile holds at sizes other than 224x224.
STAGE_SIZES = ((224, 224), (224, 320), (192, 640))


@dataclasses.dataclass(frozen=True)
class SweepLayer:
    kind: str
    in_shape: tuple[int, ...]       # without batch
    out_channels: int = 0
    kernel: int = 1
    stride: int = 1
    mode: str = "nearest"           # resize
    extra: int = 0                  # concat: second input's channels; slice: band rows


def sweep_layers(seed: int, counts: dict[str, int]) -> list[SweepLayer]:
    rng = random.Random(seed)
    out: list[SweepLayer] = []

    def spatial(c: int, side: int) -> tuple[int, int, int]:
        return (c, side, side * rng.choice((1, 1, 1, 4 // 3 + 0, 2)))

    while len([layer for layer in out if layer.kind == "pointwise"]) < counts["pointwise"]:
        cin, cout, side = rng.choice(CHANNELS), rng.choice(CHANNELS), rng.choice(SIDES)
        if cin * cout * side * side <= MAX_MACS:
            out.append(SweepLayer("pointwise", spatial(cin, side), cout))
    while len([layer for layer in out if layer.kind == "pointwise_1ch"]) < counts["pointwise_1ch"]:
        # exit heads' last layer: few to many channels, up to full resolution
        cin, side = rng.choice(CHANNELS[:10]), rng.choice(SIDES)
        out.append(SweepLayer("pointwise_1ch", spatial(cin, side), 1))
    while len([layer for layer in out if layer.kind == "depthwise"]) < counts["depthwise"]:
        c, side = rng.choice(CHANNELS), rng.choice(SIDES[:-1])
        k, s = rng.choice(((3, 1), (3, 2), (5, 1)))
        out.append(SweepLayer("depthwise", spatial(c, side), c, k, s))
    while len([layer for layer in out if layer.kind == "conv"]) < counts["conv"]:
        out.append(SweepLayer("conv", (3, rng.choice((64, 128, 224)), rng.choice((64, 128, 224))),
                              rng.choice((8, 16, 24, 32)), 3, 2))
    while len([layer for layer in out if layer.kind == "conv1d"]) < counts["conv1d"]:
        cin, cout = rng.choice((2,) + CHANNELS), rng.choice(CHANNELS)
        w = rng.choice((14, 28, 56, 112, 224, 448))
        k, s = rng.choice(((3, 2), (3, 1), (1, 1)))
        out.append(SweepLayer("conv1d", (cin, w), cout, k, s))
    while len([layer for layer in out if layer.kind == "resize"]) < counts["resize"]:
        linear = rng.random() < 0.4  # exit heads: 1 channel, bilinear, up to x16
        c = 1 if linear else rng.choice(CHANNELS)
        side = rng.choice(SIDES[:-1])
        f = rng.choice((2, 4, 8, 16)) if linear else 2
        if side * f <= 224 and c * side * side <= 2_000_000:
            out.append(SweepLayer("resize", spatial(c, side), c, 0, f, "linear" if linear else "nearest"))
    while len([layer for layer in out if layer.kind == "bilinear"]) < counts["bilinear"]:
        # exit heads' up-sampling to full resolution: one channel, from 1/2 to 1/32 of it, as two products
        side, f = rng.choice(SIDES[:-1]), rng.choice((2, 4, 8, 16, 32))
        shape = spatial(1, side)
        if side * f <= 224 and shape[2] * f <= 640:
            out.append(SweepLayer("bilinear", shape, 1, 0, f))
    while len([layer for layer in out if layer.kind == "add"]) < counts["add"]:
        c, side = rng.choice(CHANNELS[:10]), rng.choice(SIDES[:-1])
        out.append(SweepLayer("add", spatial(c, side), c))
    while len([layer for layer in out if layer.kind == "concat"]) < counts["concat"]:
        out.append(SweepLayer("concat", (rng.choice(CHANNELS), rng.choice((14, 28, 56))), 0, extra=rng.choice((16, 32, 64, 128))))
    while len([layer for layer in out if layer.kind == "slice"]) < counts["slice"]:
        c, side = rng.choice(CHANNELS), rng.choice((14, 28))
        out.append(SweepLayer("slice", (c, side, side), c, extra=rng.choice((1, 3, 5))))
    return out


DEFAULT_COUNTS = {"pointwise": 80, "pointwise_1ch": 16, "depthwise": 60, "conv": 12, "conv1d": 24, "resize": 30,
                  "bilinear": 16, "add": 20, "concat": 8, "slice": 8}
#: Kinds a host profile prices (transposed convolutions, in no candidate, fall back to conv).
HOST_KINDS = KINDS + ("pointwise_1ch", "bilinear")


def layer_graph(layer: SweepLayer) -> tuple[bytes, dict[str, np.ndarray], Workload]:
    """A one-node ONNX graph for ``layer`` (two for a bilinear one), its feeds, and its workload."""
    rng = np.random.default_rng(0)
    x_shape = (1, *layer.in_shape)
    inits, inputs = [], [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(x_shape))]
    feeds = {"x": rng.random(x_shape, dtype=np.float32)}
    k, s, kind = layer.kernel, layer.stride, layer.kind
    if kind == "bilinear":
        return _bilinear_graph(layer, inputs, feeds)
    params, macs = 0, 0
    if kind in ("pointwise", "pointwise_1ch", "depthwise", "conv", "conv1d"):
        cin = layer.in_shape[0]
        groups = cin if kind == "depthwise" else 1
        spatial = layer.in_shape[1:]
        kshape = [k] * len(spatial)
        weight = rng.standard_normal((layer.out_channels, cin // groups, *kshape)).astype(np.float32) * 0.1
        inits.append(numpy_helper.from_array(weight, "w"))
        node = helper.make_node("Conv", ["x", "w"], ["y"], group=groups, kernel_shape=kshape,
                                strides=[s] * len(spatial), pads=[k // 2] * (2 * len(spatial)))
        out_spatial = tuple((d + 2 * (k // 2) - k) // s + 1 for d in spatial)
        out_shape = (layer.out_channels, *out_spatial)
        params = weight.size
        macs = int(np.prod(out_shape)) * (cin // groups) * k ** len(spatial)
    elif kind == "resize":
        scales = np.array([1, 1, s, s], dtype=np.float32)
        inits += [numpy_helper.from_array(scales, "scales")]
        node = helper.make_node("Resize", ["x", "", "scales"], ["y"], mode=layer.mode,
                                coordinate_transformation_mode="half_pixel" if layer.mode == "linear" else "asymmetric",
                                nearest_mode="floor")
        out_shape = (layer.in_shape[0], layer.in_shape[1] * s, layer.in_shape[2] * s)
        macs = 4 * int(np.prod(out_shape)) if layer.mode == "linear" else 0
    elif kind == "add":
        inputs.append(helper.make_tensor_value_info("z", TensorProto.FLOAT, list(x_shape)))
        feeds["z"] = rng.random(x_shape, dtype=np.float32)
        node = helper.make_node("Add", ["x", "z"], ["y"])
        out_shape = layer.in_shape
    elif kind == "concat":
        z_shape = (1, layer.extra, layer.in_shape[1])
        inputs.append(helper.make_tensor_value_info("z", TensorProto.FLOAT, list(z_shape)))
        feeds["z"] = rng.random(z_shape, dtype=np.float32)
        node = helper.make_node("Concat", ["x", "z"], ["y"], axis=1)
        out_shape = (layer.in_shape[0] + layer.extra, layer.in_shape[1])
    elif kind == "slice":
        top = layer.in_shape[1] // 2 - layer.extra // 2
        for name, v in (("starts", [top]), ("ends", [top + layer.extra]), ("axes", [2])):
            inits.append(numpy_helper.from_array(np.array(v, dtype=np.int64), name))
        node = helper.make_node("Slice", ["x", "starts", "ends", "axes"], ["y"])
        out_shape = (layer.in_shape[0], layer.extra, layer.in_shape[2])
    else:
        raise ValueError(kind)
    out = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, *out_shape])
    graph = helper.make_graph([node], kind, inputs, [out], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    n_in = sum(int(np.prod(v.shape)) for v in feeds.values())
    n_out = int(np.prod(out_shape))
    if kind == "slice":
        n_in = n_out
    wl = Workload("sweep", f"{kind} {layer.in_shape}->{out_shape} k{k}/{s}", kind, tuple(layer.in_shape),
                  tuple(out_shape), k, s, macs, int(params), (n_in + params) * BYTES_PER_VALUE,
                  n_out * BYTES_PER_VALUE)
    return model.SerializeToString(), feeds, wl


def _bilinear_graph(layer: SweepLayer, inputs: list, feeds: dict[str, np.ndarray]) -> tuple[bytes, dict, Workload]:
    """The two matrix products of a bilinear up-sampling, as an exported ``ops.Resize`` holds them."""
    c, h, w = layer.in_shape
    f = layer.stride
    rows, cols = bilinear_matrix(h, f).numpy(), bilinear_matrix(w, f).numpy()
    nodes = [helper.make_node("MatMul", ["rows", "x"], ["between"]), helper.make_node("MatMul", ["between", "cols"], ["y"])]
    out = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, c, h * f, w * f])
    graph = helper.make_graph(nodes, "bilinear", inputs, [out], initializer=[
        numpy_helper.from_array(rows, "rows"), numpy_helper.from_array(np.ascontiguousarray(cols.T), "cols")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    wl = bilinear_products("sweep", f"bilinear {layer.in_shape} x{f}", layer.in_shape, f)
    return model.SerializeToString(), feeds, wl
