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

from explorer.data import frames_for_downscale
from explorer.model import AnytimeDepthNet, build_network
from explorer.space import Candidate
from explorer.supernet._stagewise import (
    Frames,
    SharedEncoder,
    StageMemo,
    evaluate_stagewise,
    feature_blocks,
    recalibrating,
)
from explorer.supernet.train import load as load_supernet
from explorer.training.train import TrainConfig, batch_row, evaluate, image_batch, train

EVALUATORS = ("supernet", "proxy")
#: the stage memo's outputs at most (:class:`explorer.supernet._stagewise.StageMemo`). A decoder stage's
#: outputs on the calibration and validation frames take 40-80 MB: replaying a default search's 178
#: candidates, 2 GiB of them spared about 15% of the stage computations that 512 MiB made, and held a
#: search at 5 GB while sampling (``bench_search_memory`` measures a search's peak)
MEMO_BYTES = 512 * 2 ** 20


@dataclass
class Evaluation:
    metrics: pd.DataFrame                 # one row per path (path 0 included)
    info: dict = field(default_factory=dict)   # evaluator name, seconds, and what it used
    network: AnytimeDepthNet | None = None
    checkpoint: Path | None = None       # trained weights on disk, when the evaluator trained


class ProxyEvaluator:
    """Stand-alone training with a short recipe. ``report(step, metrics)`` may raise
    :class:`explorer.training.train.Pruned` to stop a hopeless candidate."""

    name = "proxy"

    def __init__(self, train_set, val_set, recipe: TrainConfig, device: torch.device,
                 val_limit: int | None = None, seed: int = 0) -> None:
        self.train_set, self.val_set, self.recipe = train_set, val_set, recipe
        self.device, self.val_limit, self.seed = device, val_limit, seed

    def __call__(self, candidate: Candidate, checkpoint: Path | None = None,
                 report: Callable[[int, pd.DataFrame], None] | None = None) -> Evaluation:
        torch.manual_seed(self.seed)  # same candidate, same initial weights: results are repeatable
        net = build_network(candidate)
        train_set, val_set = (frames_for_downscale(d, candidate.downscale) for d in (self.train_set, self.val_set))
        result = train(net, train_set, val_set, self.recipe, self.device, checkpoint=checkpoint,
                       report=report, val_limit=self.val_limit, checkpoint_every=10 ** 9)
        info = {"evaluator": self.name, "seconds": result.seconds, "steps": result.steps,
                "images_per_second": result.images_per_second}
        return Evaluation(result.metrics, info, net, checkpoint)


def recalibrate_batchnorm(net: torch.nn.Module, batches: list[dict]) -> None:
    """Re-estimates every BatchNorm's running statistics as the plain average over ``batches`` (the
    supernet's statistics mix many subnets); weights are left untouched."""
    device = next(net.parameters()).device
    with recalibrating(net):
        for b in batches:
            net(image_batch(b, device), b["scan"].to(device), batch_row(b))


def loaded_batches(dataset, count: int, batch_size: int) -> list[dict]:
    """The first ``count`` items of ``dataset`` as in-memory batches (loaded once, reused)."""
    from torch.utils.data import DataLoader
    items = [dataset[i] for i in range(min(count, len(dataset)))]
    return list(DataLoader(items, batch_size=batch_size, shuffle=False))


def frames_per_batch(device: torch.device, calibration_images: int, validation_images: int) -> int:
    """A GPU runs a stage's small kernels faster than it can be handed them: each frame set as one
    batch launches 8x fewer. A CPU keeps batches of 32, whose features stay in its caches."""
    return max(calibration_images, validation_images) if device.type == "cuda" else 32


class SupernetEvaluator:
    """A candidate's slice of a trained supernet, BatchNorm recalibrated, evaluated.

    ``stagewise`` (the default) evaluates stage by stage and keeps each stage's results for the
    candidates that share it (:mod:`explorer.supernet._stagewise`: the image encoder per width, decoder
    stages and exit heads by what they read, up to ``memo_bytes`` of kept outputs); the result is
    the same as recalibrating and evaluating each candidate whole (``stagewise=False``).
    ``require_complete=False`` takes a supernet short of its steps (a search's time limit stopped it).
    ``batch_size`` (default: 32 frames on a CPU, each frame set whole on a GPU) sets how frames are batched."""

    name = "supernet"

    def __init__(self, supernet_file: str | Path, space, train_set, val_set, device: torch.device,
                 val_limit: int | None = None, calibration_images: int = 256, batch_size: int | None = None,
                 stagewise: bool = True, memo_bytes: int = MEMO_BYTES, require_complete: bool = True) -> None:
        self.file = Path(supernet_file)
        self.supernet, state = load_supernet(self.file, space, require_complete)
        self.supernet.to(device).eval()
        self.key = state["space_key"] + "-" + self.file.stem
        self.step = int(state["step"])    # the step its weights are at: an export slices the same weights
        self.device = device
        if batch_size is None:
            batch_size = frames_per_batch(device, calibration_images, val_limit or len(val_set))
        self.calibration = loaded_batches(train_set, calibration_images, batch_size)
        self.validation = loaded_batches(val_set, val_limit or len(val_set), batch_size)
        # a network working below its input size is scored on the same frames, that much larger: loaded
        # now, as the training set is not kept (see explorer.data.frames_for_downscale)
        self.downscaled = {f: (loaded_batches(frames_for_downscale(train_set, f), calibration_images, batch_size),
                               loaded_batches(frames_for_downscale(val_set, f), val_limit or len(val_set), batch_size))
                           for f in space.downscale if f > 1}
        self.stagewise = stagewise
        if stagewise:
            self._frames = Frames.of(self.calibration, device), Frames.of(self.validation, device)
            self.memo = StageMemo(memo_bytes)
        self._encoders: dict = {}

    def __call__(self, candidate: Candidate, checkpoint: Path | None = None,
                 report: Callable | None = None) -> Evaluation:
        """``candidate``'s metrics. Stage by stage, no network is made (only the stages not met
        before, one by one), and the Evaluation holds none: ``network_of`` makes it when asked."""
        t0 = time.perf_counter()
        net = None
        if candidate.downscale > 1:   # on its own frames, evaluated whole: no stage of it is read back
            net = self.network_of(candidate)
            metrics = evaluate(net, self.downscaled[candidate.downscale][1], accelerator=self.device)
        elif self.stagewise:
            metrics = evaluate_stagewise(self.supernet.stages_of(candidate), self._stage_module,
                                         self.shared_encoder(candidate.width_mult), *self._frames, self.memo)
        else:
            net = self.network_of(candidate)
            metrics = evaluate(net, self.validation, accelerator=self.device)
        info = {"evaluator": self.name, "seconds": time.perf_counter() - t0, "supernet": str(self.file),
                "supernet_key": self.key, "supernet_step": self.step}
        return Evaluation(metrics, info, net)

    def network_of(self, candidate: Candidate) -> AnytimeDepthNet:
        """``candidate``'s slice as an ordinary network, BatchNorm recalibrated: the network whose metrics
        the evaluation gives."""
        net = self.supernet.extract(candidate).to(memory_format=torch.channels_last)  # see train.image_batch
        recalibrate_batchnorm(net, self.downscaled[candidate.downscale][0] if candidate.downscale > 1 else self.calibration)
        return net.to(memory_format=torch.contiguous_format)

    def _stage_module(self, spec) -> torch.nn.Module:
        return self.supernet.extract_stage(spec).to(memory_format=torch.channels_last)

    def shared_encoder(self, width_mult: float):
        """The image encoder of ``width_mult``, recalibrated, with its features (made on first use)."""
        if width_mult not in self._encoders:
            encoder = self.supernet.extract_encoder(width_mult).to(memory_format=torch.channels_last)
            self._encoders[width_mult] = SharedEncoder(encoder, feature_blocks(self.supernet.space), *self._frames)
        return self._encoders[width_mult]
