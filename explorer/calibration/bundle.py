"""Calibration bundles: the graphs ``explorer calibrate`` measures, exported once (torch is needed
here) and packed with the probe, which runs them on a device that has only numpy and onnxruntime.

Layout (top level of the archive): ``probe.pyz`` (the ``explorer.probe`` package as a zip application),
``manifest.json`` (every graph with what the fit needs to know about it), ``layers/*.onnx`` (the
single-layer sweep) and ``stages/<candidate>/*.onnx`` (each calibration candidate's stage graphs,
in execution order).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import hashlib
import os
import tarfile
from pathlib import Path
from typing import Callable

import numpy as np
from onnx import TensorProto, load_from_string, numpy_helper

from explorer import __version__
from explorer import probe as probe_script
from explorer.calibration.sweep import (
    DEFAULT_COUNTS,
    STAGE_SIZES,
    layer_graph,
    sweep_layers,
)
from explorer.cost.precision import workload_quantized
from explorer.deploy.int8_graphs import (
    quantize_graph,
    share_model_edge_scales,
    uint8_edges,
)
from explorer.errors import UserError
from explorer.files import scratch_dir
from explorer.model import build_network
from explorer.model.onnx import example_inputs, export_segments, export_stages
from explorer.probe.pack import write_zipapp
from explorer.space import SearchSpace

#: Float initializers at least this large ship as zeros (their values do not change how long a
#: dense kernel takes), so the archive compresses to a few MB instead of hundreds.
ZERO_FROM_ELEMENTS = 64
STAGE_SEED_OFFSET = 7919
#: Calibration candidates at scale 1: a third at each of the stage sizes. Fewer fit in-sample as well
#: but predict new candidates worse (12 gave 8-16% median per-path error at the three sizes, 36
#: gave 3-10%, fitted on the same measurements).
STAGE_CANDIDATES = 36
#: Of every this many calibration candidates in a row, the first three (one per stage size) also go in
#: as int8 deployments (``precision: int8``): their deployed stage graphs (the stages between two
#: exits) quantized whole, as an int8 export quantizes them. What the int8 fit learns whole-graph
#: quantization from (tensors kept uint8 from layer to layer, quantized only at a graph's edges).
INT8_STAGE_EVERY = 9


_ZEROED = {TensorProto.FLOAT: np.float32, TensorProto.INT8: np.int8}


def _zero_weights(model: bytes) -> bytes:
    proto = load_from_string(model)
    for i, init in enumerate(proto.graph.initializer):
        if init.data_type in _ZEROED and int(np.prod(init.dims)) >= ZERO_FROM_ELEMENTS:
            zeros = np.zeros(tuple(init.dims), dtype=_ZEROED[init.data_type])
            proto.graph.initializer[i].CopyFrom(numpy_helper.from_array(zeros, init.name))
    return proto.SerializeToString()


def _int8(model: bytes, feeds: dict[str, np.ndarray]) -> bytes:
    """``model`` statically quantized as ``explorer export --quantize int8`` quantizes stage graphs."""
    with scratch_dir("int8") as tmp:
        src, dst = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        src.write_bytes(model)
        quantize_graph(src, dst, [feeds])
        return dst.read_bytes()


def _int8_graphs(net, size: tuple[int, int]) -> list[tuple[str, bytes]]:
    """``net``'s deployed stage graphs (path 0's aside) quantized as an int8 export quantizes them, each
    calibrated on what it reads on the example inputs: [(stages joined by '+', graph), ...]. The tensors
    they pass each other are uint8, as the runtime hands them between int8 graphs
    (``explorer.deploy.quantize.uint8_edges``)."""
    import torch
    graphs = export_segments(net, size)[1:]
    env = example_inputs(size)
    out = []
    with torch.no_grad():
        for desc, model in graphs:
            names = {i.name for i in load_from_string(model).graph.input}   # unused inputs were dropped
            out.append((desc["name"], _int8(model, {n: env[n].numpy() for n in desc["inputs"] if n in names})))
            for spec in net.specs:
                if spec.name in desc["stages"]:
                    net.run_stage(spec, env, size[0] // 2)
    models = [load_from_string(model) for _, model in out]
    share_model_edge_scales(models)
    uint8_edges(models)
    return [(name, model.SerializeToString()) for (name, _), model in zip(out, models)]


def stage_candidates(count: int, seed: int, exclude: set[str] = frozenset()) -> list:
    """The calibration candidates: ``count`` random default-space candidates, none of ``exclude``."""
    pool = SearchSpace.from_yaml("anytime_depth").random_candidates(count + len(exclude), seed + STAGE_SEED_OFFSET)
    return [c for c in pool if c.key not in exclude][:count]


def write_bundle_dir(folder: Path, scale: float = 1.0, seed: int = 0, n_stage: int | None = None,
                     exclude: set[str] = frozenset(), input_size: tuple[int, int] = (224, 224),
                     stage_sizes: tuple[tuple[int, int], ...] | None = None, repeats: int = 25,
                     progress: Callable[[int, int], None] | None = None, int8: bool = True
                     ) -> probe_script.BundleManifest:
    """Exports the layer sweep (``scale`` x the default counts) and the stage graphs of ``n_stage``
    candidates (default ``STAGE_CANDIDATES`` x ``scale``) into ``folder``; returns the manifest. ``int8``: every
    convolution of the sweep, and the stage graphs of some candidates (``INT8_STAGE_EVERY``), also go in
    quantized as ``explorer export --quantize int8`` quantizes (entries with ``precision: int8``), so that
    the fit prices int8 graphs too."""
    stage_sizes = stage_sizes or STAGE_SIZES
    folder = Path(folder)
    counts = {k: max(2, int(round(v * scale))) for k, v in DEFAULT_COUNTS.items()}
    layers = sweep_layers(seed, counts)
    n_stage = max(1, round(STAGE_CANDIDATES * scale)) if n_stage is None else n_stage
    cands = stage_candidates(n_stage, seed, exclude) if n_stage else []
    graphs = [layer_graph(layer) for layer in layers]
    quantized = [(layer, g) for layer, g in zip(layers, graphs) if workload_quantized(g[2])] if int8 else []
    int8_cands = {j for j in range(len(cands)) if int8 and j % INT8_STAGE_EVERY < 3}
    total = len(layers) + len(quantized) + len(cands) + len(int8_cands)
    (folder / "layers").mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256()

    def put(rel: str, data: bytes) -> None:
        (folder / rel).write_bytes(data)
        digest.update(rel.encode() + hashlib.sha256(data).digest())

    layer_entries = []
    for i, (layer, (model, feeds, wl)) in enumerate(zip(layers, graphs)):
        rel = f"layers/L{i:03d}-{layer.kind}.onnx"
        put(rel, _zero_weights(model))
        layer_entries.append({"id": f"L{i:03d}", "file": rel,
                              "inputs": [{"name": k, "shape": list(v.shape)} for k, v in feeds.items()],
                              "workload": dataclasses.asdict(wl)})
        if progress:
            progress(i + 1, total)
    for i, (layer, (model, feeds, wl)) in enumerate(quantized):
        rel = f"layers/Q{i:03d}-{layer.kind}.onnx"
        put(rel, _zero_weights(_int8(model, feeds)))
        layer_entries.append({"id": f"Q{i:03d}", "file": rel, "precision": "int8",
                              "inputs": [{"name": k, "shape": list(v.shape)} for k, v in feeds.items()],
                              "workload": dataclasses.asdict(wl)})
        if progress:
            progress(len(layers) + i + 1, total)
    cand_entries, int8_entries = [], []
    for j, cand in enumerate(cands):
        (folder / "stages" / cand.key).mkdir(parents=True, exist_ok=True)
        graphs, graphs8 = [], []
        # the stage graphs cycle through input sizes, so that the fitted profile holds at each of them
        size = tuple(stage_sizes[j % len(stage_sizes)])
        net = build_network(cand)
        for k, (spec, model) in enumerate(export_stages(net, size)[1:]):
            rel = f"stages/{cand.key}/{k:02d}-{spec.name}.onnx"
            put(rel, _zero_weights(model))
            graphs.append({"stage": spec.name, "file": rel})
        for k, (name, model) in enumerate(_int8_graphs(net, size) if j in int8_cands else []):
            rel = f"stages/{cand.key}/int8-{k:02d}.onnx"
            put(rel, _zero_weights(model))
            graphs8.append({"stage": name, "file": rel})   # several stages, joined by '+'
        entry = {"key": cand.key, "candidate": cand.to_dict(), "graphs": graphs, "input_size": list(size)}
        cand_entries.append(entry)
        if graphs8:
            int8_entries.append({**entry, "key": f"{cand.key}-int8", "graphs": graphs8, "precision": "int8"})
        if progress:
            progress(len(layers) + len(quantized) + j + 1 + len(int8_entries), total)
    cand_entries += int8_entries   # after the fp32 ones: the probe's speed check is an fp32 stage graph
    manifest = probe_script.write_bundle_manifest(
        folder, {"explorer": __version__, "created": datetime.datetime.now().isoformat(timespec="seconds"),
                 "scale": scale, "seed": seed, "input_size": list(input_size), "repeats": repeats,
                 "layers": layer_entries, "candidates": cand_entries}, digest)
    write_zipapp(folder / "probe.pyz")
    return manifest


#: The names ``explorer calibrate --bundle`` writes: the bundle is a gzip-compressed tar, which ``tar xf``
#: unpacks under any of them (docs: ``probe.tar``); another name (``.zip``) would mislead who unpacks it.
BUNDLE_SUFFIXES = (".tar", ".tar.gz", ".tgz")


def write_bundle(out: Path, **kwargs) -> probe_script.BundleManifest:
    """The bundle as one gzip-compressed tar (``tar xf`` unpacks it); written whole or not at all."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with scratch_dir("bundle") as tmp:
        manifest = write_bundle_dir(Path(tmp), **kwargs)
        part = out.with_name(f".{out.name}.part")
        try:
            with tarfile.open(part, "w:gz") as tar:
                for name in sorted(os.listdir(tmp)):
                    tar.add(os.path.join(tmp, name), arcname=name)
            os.replace(part, out)
        except OSError as exc:
            with contextlib.suppress(OSError):   # a read-only folder refuses even removing nothing
                part.unlink(missing_ok=True)
            raise UserError(f"{out}: cannot write the bundle ({exc.strerror})") from None
    return manifest
