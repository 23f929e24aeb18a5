"""``explorer calibrate``: measure a sweep of single-layer graphs on this machine with onnxruntime
and fit a CPU-style profile to them. This is what a user runs on their robot's computer."""

from __future__ import annotations

import dataclasses
import datetime
import platform
import random
from typing import Callable

import numpy as np
from onnx import TensorProto, helper, numpy_helper

from explorer.cost.devices import DeviceProfile, KindCost
from explorer.cost.fit import Observation, errors, fit_profile, fit_summary
from explorer.cost.measure import conditions, session, time_call
from explorer.cost.workloads import BYTES_PER_VALUE, KINDS, Workload

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


def _rng_layers(seed: int, counts: dict[str, int]) -> list[SweepLayer]:
    rng = random.Random(seed)
    out: list[SweepLayer] = []

    def spatial(c: int, side: int) -> tuple[int, int, int]:
        return (c, side, side * rng.choice((1, 1, 1, 4 // 3 + 0, 2)))

    while len([l for l in out if l.kind == "pointwise"]) < counts["pointwise"]:
        cin, cout, side = rng.choice(CHANNELS), rng.choice(CHANNELS + (1,)), rng.choice(SIDES)
        if cin * cout * side * side <= MAX_MACS:
            out.append(SweepLayer("pointwise", spatial(cin, side), cout))
    while len([l for l in out if l.kind == "depthwise"]) < counts["depthwise"]:
        c, side = rng.choice(CHANNELS), rng.choice(SIDES[:-1])
        k, s = rng.choice(((3, 1), (3, 2), (5, 1)))
        out.append(SweepLayer("depthwise", spatial(c, side), c, k, s))
    while len([l for l in out if l.kind == "conv"]) < counts["conv"]:
        out.append(SweepLayer("conv", (3, rng.choice((64, 128, 224)), rng.choice((64, 128, 224))),
                              rng.choice((8, 16, 24, 32)), 3, 2))
    while len([l for l in out if l.kind == "conv1d"]) < counts["conv1d"]:
        cin, cout = rng.choice((2,) + CHANNELS), rng.choice(CHANNELS)
        w = rng.choice((14, 28, 56, 112, 224, 448))
        k, s = rng.choice(((3, 2), (3, 1), (1, 1)))
        out.append(SweepLayer("conv1d", (cin, w), cout, k, s))
    while len([l for l in out if l.kind == "resize"]) < counts["resize"]:
        linear = rng.random() < 0.4  # exit heads: 1 channel, bilinear, up to x16
        c = 1 if linear else rng.choice(CHANNELS)
        side = rng.choice(SIDES[:-1])
        f = rng.choice((2, 4, 8, 16)) if linear else 2
        if side * f <= 224 and c * side * side <= 2_000_000:
            out.append(SweepLayer("resize", spatial(c, side), c, 0, f, "linear" if linear else "nearest"))
    while len([l for l in out if l.kind == "add"]) < counts["add"]:
        c, side = rng.choice(CHANNELS[:10]), rng.choice(SIDES[:-1])
        out.append(SweepLayer("add", spatial(c, side), c))
    while len([l for l in out if l.kind == "concat"]) < counts["concat"]:
        out.append(SweepLayer("concat", (rng.choice(CHANNELS), rng.choice((14, 28, 56))), 0, extra=rng.choice((16, 32, 64, 128))))
    while len([l for l in out if l.kind == "slice"]) < counts["slice"]:
        c, side = rng.choice(CHANNELS), rng.choice((14, 28))
        out.append(SweepLayer("slice", (c, side, side), c, extra=rng.choice((1, 3, 5))))
    return out


DEFAULT_COUNTS = {"pointwise": 80, "depthwise": 60, "conv": 12, "conv1d": 24, "resize": 30, "add": 20,
                  "concat": 8, "slice": 8}


def layer_graph(layer: SweepLayer) -> tuple[bytes, dict[str, np.ndarray], Workload]:
    """A one-node ONNX graph for ``layer``, its feeds, and its workload."""
    rng = np.random.default_rng(0)
    x_shape = (1, *layer.in_shape)
    inits, inputs = [], [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(x_shape))]
    feeds = {"x": rng.random(x_shape, dtype=np.float32)}
    k, s, kind = layer.kernel, layer.stride, layer.kind
    params, macs = 0, 0
    if kind in ("pointwise", "depthwise", "conv", "conv1d"):
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


def measure_sweep(layers: list[SweepLayer], threads: int | None = None, repeats: int = 15,
                  progress: Callable[[int, int], None] | None = None) -> list[tuple[Workload, float]]:
    out = []
    for i, layer in enumerate(layers):
        model, feeds, wl = layer_graph(layer)
        sess = session(model, threads)
        out.append((wl, time_call(lambda: sess.run(None, feeds), 3, repeats)))
        if progress:
            progress(i + 1, len(layers))
    return out


def measure_stages(count: int, seed: int, threads: int | None, repeats: int,
                   input_size: tuple[int, int] = (224, 224), exclude: set[str] = frozenset(),
                   progress: Callable[[int, int], None] | None = None) -> list[Observation]:
    """Whole stage graphs of random candidates of the default space: layers in context (fused,
    sharing caches and threads) run faster than alone, and only multi-layer graphs tell a per-layer
    cost from a per-launch one."""
    from explorer.cost import candidate_cost
    from explorer.cost.measure import measure_network
    from explorer.model import build_network
    from explorer.space import SearchSpace
    space = SearchSpace.from_yaml("anytime_depth")
    pool = [c for c in space.enumerate() if c.key not in exclude]
    cands = random.Random(seed).sample(pool, count)
    obs = []
    for i, cand in enumerate(cands):
        m = measure_network(build_network(cand), input_size, threads, repeats, whole=False)
        cost = candidate_cost(cand, input_size)
        for stage, ms in m.stage_ms.items():
            wl = [w for w in cost.workloads if w.stage == stage]
            obs.append(Observation(f"{cand.key}/{stage}", wl, ms, weight=4.0, stages=1))
        if progress:
            progress(i + 1, count)
    return obs


def fit_host(measured: list[tuple[Workload, float]], name: str = "host",
             description: str | None = None, cond: dict | None = None,
             stage_obs: list[Observation] = ()) -> DeviceProfile:
    obs = [Observation(w.layer, [w], ms, stages=1) for w, ms in measured] + list(stage_obs)
    base = DeviceProfile(
        name=name, description=description or f"{platform.node() or 'this machine'} CPU, onnxruntime",
        overlap=False, bandwidth_gbs=10.0, kinds={k: KindCost(20.0, 0.005) for k in KINDS},
        stage_overhead_ms=0.02)
    ident = {k: k for k in KINDS}
    rate_of = {k: k for k in ("conv", "pointwise", "depthwise", "conv1d", "resize")}
    best, best_err = None, None
    for overlap in (False, True):
        p = fit_profile(dataclasses.replace(base, overlap=overlap), obs, rate_of, ident,
                        free_inference=False, free_stage=True,
                        own_bandwidth=KINDS)
        err = float(errors(p, obs)["error"].abs().median())
        if best_err is None or err < best_err:
            best, best_err = p, err
    layers = errors(best, obs[:len(measured)])
    summary = [fit_summary(layers, f"{len(measured)} single-layer graphs measured here")]
    if stage_obs:
        summary.append(fit_summary(errors(best, list(stage_obs)), f"{len(stage_obs)} stage graphs of "
                                   "random candidates measured here"))
    per_kind = {k: round(float(layers[[w.kind == k for w, _ in measured]]["error"].abs().median()), 4)
                for k in KINDS if any(w.kind == k for w, _ in measured)}
    return dataclasses.replace(best, provenance={
        "calibrated": True,
        "sources": [f"explorer calibrate on {platform.node()} at "
                    f"{datetime.datetime.now().isoformat(timespec='seconds')}"],
        "conditions": cond or conditions(),
        "fit": summary, "median_abs_error_per_kind": per_kind, "checks": []})


def calibrate(threads: int | None = None, repeats: int = 25, seed: int = 0, scale: float = 1.0,
              progress: Callable[[int, int], None] | None = None, name: str = "host",
              stage_candidates: int | None = None, exclude: set[str] = frozenset()) -> DeviceProfile:
    """Layer sweep plus the stages of ``stage_candidates`` random default-space candidates (none
    of ``exclude``, candidate keys), then the fit."""
    counts = {k: max(2, int(round(v * scale))) for k, v in DEFAULT_COUNTS.items()}
    layers = _rng_layers(seed, counts)
    n_stage = max(1, round(12 * scale)) if stage_candidates is None else stage_candidates
    total = len(layers) + n_stage
    measured = measure_sweep(layers, threads, repeats,
                             (lambda i, n: progress(i, total)) if progress else None)
    stage_obs: list[Observation] = []
    per_size = [n_stage // len(STAGE_SIZES) + (i < n_stage % len(STAGE_SIZES)) for i in range(len(STAGE_SIZES))]
    for i, (size, count) in enumerate(zip(STAGE_SIZES, per_size)):
        done = len(layers) + sum(per_size[:i])
        if count:
            stage_obs += measure_stages(count, seed + 7919 + i, threads, repeats, size, exclude=exclude,
                                        progress=(lambda j, n, d=done: progress(d + j, total)) if progress else None)
    return fit_host(measured, name=name, cond=conditions(threads, repeats), stage_obs=stage_obs)
