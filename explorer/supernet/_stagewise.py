"""Supernet evaluation one stage at a time, each stage's result kept for the candidates that share it.

A candidate's slice of the supernet is evaluated by recalibrating its BatchNorm statistics on the
calibration frames (training mode) and then running the validation frames (eval mode). A stage's
weights come from its supernet slot and config, and its inputs from the stages before it, so its
recalibrated statistics, its outputs on both frame sets and (for an exit) its path metrics depend
only on a key: (stage name, config, keys of its inputs). Run stage by stage over all batches instead
of batch by batch over all stages, a candidate reuses every stage it shares with one evaluated
before: in a search the sampler keeps proposing variations of the best candidates, so many of the
stages are already known.

The image encoder is shared by width (:class:`SharedEncoder`): its features at every block count
any candidate reads, so encoder segments split differently by encoder exits still share their work.
"""

from __future__ import annotations

from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Hashable

import pandas as pd
import torch

from explorer.metrics import MetricAverager, batch_depth_metrics
from explorer.model.exits import ExitHead, interpolate_scan
from explorer.model.image_encoder import ImageEncoder, ImageEncoderConfig
from explorer.model.network import StageSpec
from explorer.space import MOBILENET_V1_BLOCKS
from explorer.training.train import batch_row, image_batch


def _norms(module: torch.nn.Module) -> list[torch.nn.modules.batchnorm._BatchNorm]:
    return [m for m in module.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


@contextmanager
def recalibrating(module: torch.nn.Module):
    """Training mode without gradients, every BatchNorm of ``module`` reset to average its statistics
    over the batches run inside (cumulatively), exit heads' resize skipped (their outputs are thrown
    away; a residual head's sum with the full-size scan needs its full size); eval mode after."""
    norms = _norms(module)
    momenta = [m.momentum for m in norms]
    heads = [m for m in module.modules() if isinstance(m, ExitHead) and not m.config.residual]
    factors = [h.resize.factor for h in heads]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None
    module.train()
    try:
        for h in heads:
            h.resize.factor = 1
        with torch.no_grad():
            yield
    finally:
        for h, f in zip(heads, factors):
            h.resize.factor = f
        for m, momentum in zip(norms, momenta):
            m.momentum = momentum
        module.eval()


def feature_blocks(space) -> set[int]:
    """Every block count at which some candidate of ``space`` reads the image encoder: its ends
    (truncation, encoder exits) and the skips before stride-2 blocks."""
    deepest = max(space.encoder_blocks)
    skips = {i for i in range(deepest) if MOBILENET_V1_BLOCKS[i][2] == 2}
    return set(space.encoder_blocks) | set(space.optional_encoder_exits) | skips


@dataclass
class Frames:
    """Ready inputs of one frame set: per batch the image (on the device, channels-last), the scan,
    its row, and the dense depth (validation only)."""

    images: list[torch.Tensor]
    scans: list[torch.Tensor]
    rows: list[int]
    depths: list[torch.Tensor | None]

    @classmethod
    def of(cls, batches: list[dict], device: torch.device) -> "Frames":
        return cls([image_batch(b, device) for b in batches], [b["scan"].to(device) for b in batches],
                   [batch_row(b) for b in batches], [b.get("depth") for b in batches])


class SharedEncoder:
    """One width's whole image encoder, recalibrated once, and its features on the calibration
    (training mode: batch statistics, as recalibration sees them) and validation frames."""

    def __init__(self, encoder: ImageEncoder, blocks: set[int], calibration: Frames, validation: Frames) -> None:
        self.width_mult = encoder.config.width_mult
        with recalibrating(encoder):
            self.calibration = [encoder.block_features(x, blocks) for x in calibration.images]
        with torch.no_grad():
            self.validation = [encoder.block_features(x, blocks) for x in validation.images]


@dataclass
class _StageResult:
    calibration: list[tuple[torch.Tensor, ...]] | None     # training-mode outputs (not kept for exits)
    validation: list[tuple[torch.Tensor, ...]] | None      # eval-mode outputs (not kept for exits)
    metrics: dict[str, float] = field(default_factory=dict)   # an exit's path metrics
    nbytes: int = 0


class StageMemo:
    """Stage results by key, least recently used dropped beyond ``max_bytes`` of kept outputs. An exit's
    result (its path metrics, no tensors) is kept apart, whatever the bytes: it costs nothing to keep,
    and in one LRU with the decoders' outputs (tens of MB each) a small memo dropped it with them."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.entries: OrderedDict[Hashable, _StageResult] = OrderedDict()
        self.exits: dict[Hashable, _StageResult] = {}
        self.nbytes = 0
        self.hits = self.misses = 0
        self.path_0: dict[str, float] | None = None

    def get(self, key: Hashable) -> _StageResult | None:
        entry = self.exits.get(key)
        if entry is None:
            entry = self.entries.get(key)
            if entry is not None:
                self.entries.move_to_end(key)
        if entry is None:
            self.misses += 1
            return None
        self.hits += 1
        return entry

    def put(self, key: Hashable, entry: _StageResult) -> None:
        if entry.calibration is None and entry.validation is None:
            self.exits[key] = entry
            return
        if entry.nbytes > self.max_bytes:
            return
        self.entries[key] = entry
        self.nbytes += entry.nbytes
        while self.nbytes > self.max_bytes:
            _, old = self.entries.popitem(last=False)
            self.nbytes -= old.nbytes


def _nbytes(outputs: list[tuple[torch.Tensor, ...]]) -> int:
    return sum(t.numel() * t.element_size() for outs in outputs for t in outs)


def _path_metrics(outputs: list[torch.Tensor], depths: list[torch.Tensor]) -> dict[str, float]:
    averager = MetricAverager()
    for out, depth in zip(outputs, depths):
        for m in batch_depth_metrics(out.float().cpu(), depth):
            averager.add(m)
    return averager.result()


def _run_stage(module: torch.nn.Module, spec: StageSpec, calibration: list[dict], validation: list[dict],
               cal_frames: Frames, val_frames: Frames) -> _StageResult:
    """Recalibrates the stage's statistics on the calibration inputs, then runs the validation ones."""

    def call(env: dict, row: int):
        args = [env[n] for n in spec.inputs] + ([row] if spec.uses_scan_row else [])
        out = module(*args)
        return out if isinstance(out, tuple) else (out,)

    exit_stage = spec.path is not None
    cal_outs = None
    # an exit's outputs feed nothing: without statistics to recalibrate it need not run here
    if _norms(module) or not exit_stage:
        with recalibrating(module):
            cal_outs = [call(env, row) for env, row in zip(calibration, cal_frames.rows)]
    module.eval()
    with torch.no_grad():
        val_outs = [call(env, row) for env, row in zip(validation, val_frames.rows)]
    if exit_stage:
        return _StageResult(None, None, _path_metrics([o[0] for o in val_outs], val_frames.depths))
    return _StageResult(cal_outs, val_outs, nbytes=_nbytes(cal_outs) + _nbytes(val_outs))


def evaluate_stagewise(specs: list[StageSpec], stage_module: Callable[[StageSpec], torch.nn.Module],
                       encoder: SharedEncoder, cal_frames: Frames, val_frames: Frames, memo: StageMemo) -> pd.DataFrame:
    """The per-path metrics on the validation frames of the network of stages ``specs``, its statistics
    recalibrated, exactly as :func:`explorer.supernet.evaluators.recalibrate_batchnorm` then
    :func:`explorer.training.train.evaluate` would give them, reusing what ``memo`` and ``encoder``
    hold. ``stage_module(spec)`` makes a stage's module with its weights, for the stages ``memo``
    lacks: the others are never built."""
    calibration = [{"image": x, "scan": s} for x, s in zip(cal_frames.images, cal_frames.scans)]
    validation = [{"image": x, "scan": s} for x, s in zip(val_frames.images, val_frames.scans)]
    keys: dict[str, Hashable] = {"image": "image", "scan": "scan"}
    if memo.path_0 is None:    # the scan's own path: the same for every candidate
        height = val_frames.images[0].shape[2]
        memo.path_0 = _path_metrics([interpolate_scan(s, height) for s in val_frames.scans], val_frames.depths)
    rows = [{"path": 0, **memo.path_0}]
    for spec in specs:
        if isinstance(spec.config, ImageEncoderConfig):
            for name, block in zip(spec.outputs, spec.config.output_blocks()):
                keys[name] = ("encoder", encoder.width_mult, block)
                for env, features in zip(calibration, encoder.calibration):
                    env[name] = features[block]
                for env, features in zip(validation, encoder.validation):
                    env[name] = features[block]
            continue
        key = (spec.name, spec.config, tuple(keys[n] for n in spec.inputs))
        result = memo.get(key)
        if result is None:
            result = _run_stage(stage_module(spec), spec, calibration, validation, cal_frames, val_frames)
            memo.put(key, result)
        for i, name in enumerate(spec.outputs):
            keys[name] = (key, i)
        if spec.path is not None:
            rows.append({"path": spec.path, **result.metrics})
            continue
        for env, outs in zip(calibration, result.calibration):
            env.update(zip(spec.outputs, outs))
        for env, outs in zip(validation, result.validation):
            env.update(zip(spec.outputs, outs))
    return pd.DataFrame(rows)
