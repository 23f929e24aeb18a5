"""How a candidate's accuracy is estimated during a search: two evaluators, one interface.

- ``proxy``: train the candidate alone with a short recipe (about 20 s at 64x64 on 2 cores).
- ``supernet``: take the candidate's slice of a trained weight-sharing supernet, recalibrate its
  BatchNorm statistics on a few training batches, evaluate (about a second).

Both return an :class:`Evaluation`: per-path metrics on the validation set plus what produced them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pandas as pd
import torch

from explorer.model import AnytimeDepthNet, build_network
from explorer.space import Candidate
from explorer.train import TrainConfig, _batch_row, evaluate, image_batch, train

EVALUATORS = ("supernet", "proxy")


@dataclass
class Evaluation:
    metrics: pd.DataFrame                 # one row per path (path 0 included)
    info: dict = field(default_factory=dict)   # evaluator name, seconds, and what it used
    network: AnytimeDepthNet | None = None
    checkpoint: Path | None = None       # trained weights on disk, when the evaluator trained


class ProxyEvaluator:
    """Stand-alone training with a short recipe. ``report(step, metrics)`` may raise
    :class:`explorer.train.Pruned` to stop a hopeless candidate."""

    name = "proxy"

    def __init__(self, train_set, val_set, recipe: TrainConfig, device: torch.device,
                 val_limit: int | None = None, seed: int = 0) -> None:
        self.train_set, self.val_set, self.recipe = train_set, val_set, recipe
        self.device, self.val_limit, self.seed = device, val_limit, seed

    def __call__(self, candidate: Candidate, checkpoint: Path | None = None,
                 report: Callable[[int, pd.DataFrame], None] | None = None) -> Evaluation:
        torch.manual_seed(self.seed)  # same candidate, same initial weights: results are repeatable
        net = build_network(candidate)
        result = train(net, self.train_set, self.val_set, self.recipe, self.device, checkpoint=checkpoint,
                       report=report, val_limit=self.val_limit, checkpoint_every=10 ** 9)
        info = {"evaluator": self.name, "seconds": result.seconds, "steps": result.steps,
                "images_per_second": result.images_per_second}
        return Evaluation(result.metrics, info, net, checkpoint)


def recalibrate_batchnorm(net: torch.nn.Module, batches: list[dict]) -> None:
    """Re-estimates every BatchNorm's running statistics as the plain average over ``batches`` (the
    supernet's statistics mix many subnets); weights are left untouched. Batches that carry
    ``encoder_features`` leave the image encoder's statistics alone (they came with the features)."""
    from explorer.model.exits import ExitHead
    from explorer.model.image_encoder import ImageEncoder
    shared = {id(m) for e in net.modules() if isinstance(e, ImageEncoder) for m in e.modules()} \
        if batches and "encoder_features" in batches[0] else set()
    norms = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm) and id(m) not in shared]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    # the exits' outputs are thrown away here: skip their resize to full resolution
    heads = [m for m in net.modules() if isinstance(m, ExitHead)]
    factors = [h.resize.factor for h in heads]
    device = next(net.parameters()).device
    net.train()
    try:
        for h in heads:
            h.resize.factor = 1
        with torch.no_grad():
            for b in batches:
                net(image_batch(b, device), b["scan"].to(device), _batch_row(b),
                    encoder_features=b.get("encoder_features"))
    finally:
        for h, f in zip(heads, factors):
            h.resize.factor = f
        for m, momentum in zip(norms, momenta):
            m.momentum = momentum
    net.eval()


def _batches(dataset, count: int, batch_size: int) -> list[dict]:
    """The first ``count`` items of ``dataset`` as in-memory batches (loaded once, reused)."""
    from torch.utils.data import DataLoader
    items = [dataset[i] for i in range(min(count, len(dataset)))]
    return list(DataLoader(items, batch_size=batch_size, shuffle=False))


class SupernetEvaluator:
    """A candidate's slice of a trained supernet, BatchNorm recalibrated, evaluated.

    Candidates of one width share their image encoder's work (``share_encoder``): a block's
    recalibrated statistics and outputs depend only on the blocks before it, so the whole encoder
    of each width runs once over the calibration and validation frames and every candidate of that
    width reads its features (and statistics) from there; only its LiDAR, ECU and decoder run."""

    name = "supernet"

    def __init__(self, supernet_file: str | Path, space, train_set, val_set, device: torch.device,
                 val_limit: int | None = None, calibration_images: int = 256, batch_size: int = 32,
                 share_encoder: bool = True) -> None:
        from explorer.supernet import load_supernet
        self.file = Path(supernet_file)
        self.supernet, state = load_supernet(self.file, space)
        self.supernet.to(device).eval()
        self.key = state["space_key"] + "-" + self.file.stem
        self.device = device
        self.calibration = _batches(train_set, calibration_images, batch_size)
        self.validation = _batches(val_set, val_limit or len(val_set), batch_size)
        self.share_encoder = share_encoder
        self._encoders: dict[float, _SharedEncoder] = {}

    def __call__(self, candidate: Candidate, checkpoint: Path | None = None,
                 report: Callable | None = None) -> Evaluation:
        t0 = time.perf_counter()
        net = self.supernet.extract(candidate).to(memory_format=torch.channels_last)  # see train.image_batch
        calibration, validation = self.calibration, self.validation
        if self.share_encoder:
            shared = self._shared_encoder(candidate.width_mult)
            shared.load_statistics(net)
            calibration, validation = shared.calibration, shared.validation
        recalibrate_batchnorm(net, calibration)
        metrics = evaluate(net, validation, device=self.device)
        net.to(memory_format=torch.contiguous_format)
        info = {"evaluator": self.name, "seconds": time.perf_counter() - t0, "supernet": str(self.file),
                "supernet_key": self.key}
        return Evaluation(metrics, info, net)

    def _shared_encoder(self, width_mult: float) -> "_SharedEncoder":
        if width_mult not in self._encoders:
            encoder = self.supernet.extract_encoder(width_mult).to(memory_format=torch.channels_last)
            self._encoders[width_mult] = _SharedEncoder(encoder, _feature_blocks(self.supernet.space),
                                                        self.calibration, self.validation, self.device)
        return self._encoders[width_mult]


def _feature_blocks(space) -> set[int]:
    """Every block count at which some candidate of ``space`` reads the image encoder: its ends
    (truncation, encoder exits) and the skips before stride-2 blocks."""
    from explorer.space import MOBILENET_V1_BLOCKS
    deepest = max(space.encoder_blocks)
    skips = {i for i in range(deepest) if MOBILENET_V1_BLOCKS[i][2] == 2}
    return set(space.encoder_blocks) | set(space.optional_encoder_exits) | skips


class _SharedEncoder:
    """One width's whole image encoder, recalibrated once, and its features on the calibration
    (training mode: batch statistics, as recalibration sees them) and validation frames."""

    def __init__(self, encoder, blocks: set[int], calibration: list[dict], validation: list[dict],
                 device: torch.device) -> None:
        norms = [m for m in encoder.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
        for m in norms:
            m.reset_running_stats()
            m.momentum = None
        with torch.no_grad():
            encoder.train()
            self.calibration = [dict(b, encoder_features=encoder.block_features(image_batch(b, device), blocks))
                                for b in calibration]
            encoder.eval()
            self.validation = [dict(b, encoder_features=encoder.block_features(image_batch(b, device), blocks))
                               for b in validation]
        self.statistics = dict(encoder.named_buffers())

    def load_statistics(self, net: AnytimeDepthNet) -> None:
        """Copies the recalibrated statistics into ``net``'s image encoder stages."""
        from explorer.model.image_encoder import ImageEncoderConfig
        from explorer.supernet._slicing import super_name
        with torch.no_grad():
            for spec in net.specs:
                if isinstance(spec.config, ImageEncoderConfig):
                    for local, buffer in net.stages[spec.name].named_buffers():
                        buffer.copy_(self.statistics[super_name(spec, local).removeprefix("image_encoder.")])
