"""Training a network for the size it is deployed at: most steps at a small training size (cheap), then
a short tuning phase at the deployment size, then every path measured there.

A network trained at 64x64 and run at 224x224 sees objects three times larger in pixels than it
learned, and its BatchNorm statistics no longer match its activations: its exits lose most of what
they gained over the scan. A few steps of training at the deployment size repair that, as FixRes
("Fixing the train-test resolution discrepancy", Touvron et al., 2019) found for classification.
``bench_resolution`` compares this with training only small, training at the
deployment size from the start and progressive resizing, at equal time (its record holds the figures).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from explorer.data import frames_for_downscale
from explorer.training.memory import release_host_memory
from explorer.training.train import TrainConfig, TrainResult, train

#: the tuning phase's learning rate, as a fraction of the recipe's (it continues a trained network)
TUNE_LR_SCALE = 0.25
#: the most frames the tuning runs through the network at once: its steps' activations at the deployment
#: size are the most a search holds (over a gigabyte for 16 frames at 224x224), so a batch is split into
#: parts of this many, one after another (the same mean gradient; BatchNorm's statistics per part)
TUNE_PART_FRAMES = 8


@dataclass(frozen=True)
class DeploymentRecipe:
    """``train`` at its own input size, then ``tune_steps`` steps at ``deploy_size`` (none when the two
    sizes are the same); the result is measured at ``deploy_size``."""

    train: TrainConfig
    deploy_size: tuple[int, int]
    tune_steps: int = 20

    @property
    def tunes(self) -> bool:
        return self.tune_steps > 0 and tuple(self.deploy_size) != tuple(self.train.input_size)

    def tune_config(self) -> TrainConfig:
        """The tuning phase: the same recipe at the deployment size, a lower learning rate."""
        lr = self.train.lr * TUNE_LR_SCALE
        return dataclasses.replace(self.train, steps=self.tune_steps, input_size=tuple(self.deploy_size), lr=lr,
                                   lr_end=lr / 10, eval_every=0,
                                   micro_batches=-(-self.train.batch_size // TUNE_PART_FRAMES))

    def to_dict(self) -> dict:
        """What a finalist's record keeps: the first phase's recipe (its keys as before), the deployment
        size and the tuning steps."""
        return {**self.train.to_dict(), "deploy_size": list(self.deploy_size),
                "tune_steps": self.tune_steps if self.tunes else 0}


@dataclass(frozen=True)
class DeploymentData:
    """The frames a deployment-size training reads: the training set at the training size, and the
    training and validation sets at the deployment size (the validation set is what every path is
    measured on)."""

    train: object
    deploy_train: object
    deploy_val: object


def train_for_deployment(net, data: DeploymentData, recipe: DeploymentRecipe, accelerator: torch.device | None,
                         checkpoint: Path | None = None, val_limit: int | None = None) -> TrainResult:
    """Trains ``net`` with ``recipe`` and returns the result with its per-path metrics measured at the
    deployment size on the first ``val_limit`` validation frames. Each phase checkpoints on its own
    file (``checkpoint`` and its ``-tune`` sibling), so a killed run resumes in the phase it was in."""
    # a network working below its input size trains at the training size on frames that much larger
    small = frames_for_downscale(data.train, getattr(getattr(net, "candidate", None), "downscale", 1))
    if not recipe.tunes:   # measured where it is deployed, whatever size it was trained at
        return train(net, small, data.deploy_val, recipe.train, accelerator, checkpoint=checkpoint,
                     val_limit=val_limit)
    # no validation pass at the training size ([] evaluates nothing): its figures are not the network's
    first = train(net, small, [], recipe.train, accelerator, checkpoint=checkpoint)
    # a training step's activations at the deployment size are the most a search allocates at once (see
    # TUNE_PART_FRAMES): the tuning starts from the pages what ran before it freed
    release_host_memory()
    tune_checkpoint = None if checkpoint is None else checkpoint.with_name(f"{checkpoint.stem}-tune{checkpoint.suffix}")
    tuned = train(net, data.deploy_train, data.deploy_val, recipe.tune_config(), accelerator, checkpoint=tune_checkpoint,
                  val_limit=val_limit)
    if tune_checkpoint is not None and checkpoint is not None:
        tune_checkpoint.replace(checkpoint)   # one file: the network as measured
    return TrainResult(tuned.metrics, first.history + tuned.history, first.seconds + tuned.seconds,
                       _rate(first, tuned), first.steps + tuned.steps)


def _rate(*results: TrainResult) -> float:
    seconds = sum(r.seconds for r in results)
    images = sum(r.images_per_second * r.seconds for r in results)
    return images / seconds if seconds > 0 else 0.0
