"""The network that ships: a trained candidate less the exits that do not improve on an earlier path.

An anytime network is worth its early paths only where each one is more accurate than what is
already in hand. After training, an exit whose measured error is not lower than that of an earlier
path (path 0, the interpolated scan, included) is dropped: its head is not computed, so every later
path is ready sooner. What it read stays where a later stage needs it (an exit head is a leaf of the
stage graph). The shipped network is itself a candidate of the family, with fewer exits, and its
weights are those of the trained network (:func:`carry_weights`): no retraining.

The last exit is never dropped (the candidate family always exits after its last decoder stage); where
it is not the most accurate path, the runtime's rule, returning the most accurate path ready, covers it.
Nor is an exit whose depth map a later stage reads: that stage would lose an input it was trained on.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch
from torch import nn

from explorer.model.network import build_network, stage_specs
from explorer.space import Candidate


@dataclass(frozen=True)
class DroppedExit:
    """An exit left out of the shipped network: its path in the trained network, its head's stage
    name, its error, and the earlier path (with its error) that was at least as accurate;
    ``measured_on``: where those errors come from when not the study's own figures (an export's graphs)."""

    path: int
    exit: str
    loss: float
    better_path: int
    better_loss: float
    measured_on: str = ""

    def to_dict(self) -> dict:
        data = dataclasses.asdict(self)
        if not self.measured_on:
            del data["measured_on"]
        return data

    @classmethod
    def from_dict(cls, data: Mapping) -> "DroppedExit":
        return cls(int(data["path"]), str(data["exit"]), float(data["loss"]), int(data["better_path"]),
                   float(data["better_loss"]), str(data.get("measured_on") or ""))

    def describe(self, metric: str = "error") -> str:
        where = f", measured on {self.measured_on}" if self.measured_on else ""
        return (f"{self.exit} (path {self.path} as trained) dropped: {metric} {self.loss:.4g} is not below "
                f"{self.better_loss:.4g}, path {self.better_path}'s as trained{where}")


@dataclass(frozen=True)
class ShippedNetwork:
    """``candidate`` as shipped: its exits less ``dropped``; ``paths`` lists, for each path of the
    shipped network (path 0 included), its path in the trained network."""

    trained: Candidate
    candidate: Candidate
    paths: tuple[int, ...]
    dropped: tuple[DroppedExit, ...] = ()

    def losses(self, path_losses: Sequence[float]) -> list[float]:
        """The trained network's per-path losses, kept for the shipped network's paths."""
        return [float(path_losses[p]) for p in self.paths]


def exit_names(candidate: Candidate) -> list[str]:
    """The stage name of each path's exit head, for paths 1..K in order."""
    return [s.name for s in stage_specs(candidate) if s.path is not None]


def without_exits(candidate: Candidate, names: Sequence[str]) -> Candidate:
    """``candidate`` with the exit heads ``names`` (stage names, as :func:`exit_names` gives) left out."""
    names = set(names)
    if not names:
        return candidate
    stages = len(candidate.decoder_widths)
    if f"exit_{stages}" in names:
        raise ValueError("the last decoder stage's exit cannot be left out")
    exits = tuple(e for e in candidate.exits if f"exit_{e}" not in names)
    encoder_exits = tuple(k for k in candidate.encoder_exits if f"exit_b{k}" not in names)
    return dataclasses.replace(candidate, exits=exits, encoder_exits=encoder_exits,
                               lidar_exit=candidate.lidar_exit and "lidar_exit" not in names)


def ship(candidate: Candidate, path_losses: Sequence[float], keep_every_exit: bool = False) -> ShippedNetwork:
    """The network to ship from ``candidate`` given its per-path losses (path 0 included; lower is
    better): every exit whose loss is not below the best of the paths before it is dropped, the last
    excepted, and those whose depth map a later stage reads. A NaN loss never improves.
    ``keep_every_exit``: ship the network as trained."""
    if len(path_losses) != candidate.num_paths:
        raise ValueError(f"{len(path_losses)} losses for the {candidate.num_paths} paths of {candidate.key}")
    names = exit_names(candidate)
    read = {i for s in stage_specs(candidate) for i in s.inputs}   # an exit a later stage reads stays
    best, best_path = float(path_losses[0]), 0
    dropped: list[DroppedExit] = []
    for path in range(1, candidate.num_paths):
        loss = float(path_losses[path])
        improves = not math.isnan(loss) and (math.isnan(best) or loss < best)
        last = path == candidate.num_paths - 1
        if improves:
            best, best_path = loss, path
        elif not keep_every_exit and not last and f"depth_{path}" not in read:
            dropped.append(DroppedExit(path, names[path - 1], loss, best_path, best))
    gone = {d.path for d in dropped}
    shipped = without_exits(candidate, [d.exit for d in dropped])
    return ShippedNetwork(candidate, shipped, tuple(p for p in range(candidate.num_paths) if p not in gone),
                          tuple(dropped))


def last_path_note(path_losses: Sequence[float], metric: str = "error") -> str | None:
    """A line for a shipped network (its per-path losses, path 0 included) whose last path is not more
    accurate than an earlier one, which :func:`ship` keeps: that a halt after it returns the earlier
    path, as the anytime loss counts it and the runtime does. None where the last path is the best."""
    last = float(path_losses[-1]) if len(path_losses) > 1 else math.nan
    earlier = [(float(loss), path) for path, loss in enumerate(path_losses[:-1]) if not math.isnan(float(loss))]
    if math.isnan(last) or not earlier or last < min(earlier)[0]:
        return None
    best, path = min(earlier)
    return (f"the last path (path {len(path_losses) - 1}) is not below path {path}'s {metric} ({last:.4g} against "
            f"{best:.4g}): it ships, as the last stage always exits, but a halt after it returns path {path}")


_ENCODER_BLOCK = re.compile(r"^stages\.(image_encoder(?:_(\d+))?)\.blocks\.(\d+)\.(.*)$")


def carry_weights(state: Mapping[str, torch.Tensor], trained: Candidate,
                  shipped: Candidate) -> dict[str, torch.Tensor]:
    """The state dict of ``shipped`` (the ``trained`` candidate less some exits) taken from
    ``trained``'s ``state``: the heads left out are left behind, and the image encoder's blocks are
    renumbered where leaving out an encoder exit joins two of its segments into one stage."""
    def segment_of(block: int, candidate: Candidate) -> tuple[str, int]:
        start = 0
        for k in (*candidate.encoder_exits, candidate.encoder_blocks):
            if block < k:
                return ("image_encoder" if start == 0 else f"image_encoder_{start + 1}"), block - start
            start = k
        raise ValueError(f"block {block} lies outside a {candidate.encoder_blocks}-block encoder")

    starts = {("image_encoder" if s == 0 else f"image_encoder_{s + 1}"): s
              for s in (0, *trained.encoder_exits)}
    wanted = {s.name for s in stage_specs(shipped)}
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        match = _ENCODER_BLOCK.match(key)
        if match:
            block = starts[match.group(1)] + int(match.group(3))
            stage, local = segment_of(block, shipped)
            out[f"stages.{stage}.blocks.{local}.{match.group(4)}"] = value
        elif key.split(".")[1] in wanted:
            out[key] = value
    return out


def shipped_network(trained: nn.Module, shipped: Candidate) -> nn.Module:
    """The network of ``shipped`` (``trained.candidate`` less some exits) with ``trained``'s weights, in
    the same mode (training or evaluation)."""
    if shipped == trained.candidate:
        return trained
    net = build_network(shipped)
    net.load_state_dict(carry_weights(trained.state_dict(), trained.candidate, shipped))
    return net.train(trained.training)
