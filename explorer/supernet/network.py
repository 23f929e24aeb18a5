"""A weight-sharing supernet over a search space (Once-for-All style).

The supernet is the space's largest network, built from the same stage configs as any candidate,
plus every exit head any candidate can have (each head depth, every exit position, the fused encoder
exits and the LiDAR-only exit). A candidate is a set of views into these tensors (first blocks, first
channels, first layers): :meth:`Supernet.forward_subnet` runs it for training without copying a
weight, :meth:`Supernet.extract` returns an ordinary :class:`AnytimeDepthNet` carrying copies of its
slices, so evaluation, export, fine-tuning and the runtime never know where the weights came from.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import random
from collections import OrderedDict

import torch
from torch import nn
from torch.func import functional_call

from explorer.errors import UserError
from explorer.model import AnytimeDepthNet, build_network, stage_specs
from explorer.model.image_encoder import ImageEncoder, ImageEncoderConfig
from explorer.model.network import StageSpec
from explorer.space import Candidate, SearchSpace
from explorer.supernet._graphs import StageGraphs
from explorer.supernet._slicing import slice_of, slot_of, super_name


def space_identity(space: SearchSpace) -> dict:
    """What a supernet depends on in a space: its dimensions, not its name or description (nor the
    precisions it lists: int8 candidates are fp32 weights quantized afterwards; nor the sizes its
    networks work at: a network working at half its input size has the weights of its twin at full
    size, and it trains on frames twice the size, so that it works at the training size as its twin does)."""
    dims = {k: list(v) for k, v in space.dimensions().items() if k not in ("precision", "downscale")}
    dims["required_exits"] = list(space.required_exits)
    dims["decoder_stages"] = len(space.decoder_widths)
    if space.exit_residual != (False,):   # spaces without residual exits keep the keys they had
        dims["exit_residual"] = list(space.exit_residual)
    return dims


def space_key(space: SearchSpace) -> str:
    text = json.dumps(space_identity(space), sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:10]


#: the Candidate fields of exit heads sized for their position (0: as head_depth / head_width)
HEAD_FIELDS = ("encoder_head_depth", "encoder_head_width", "ecu_head_depth", "ecu_head_width")


def _extreme_candidate(space: SearchSpace, pick, head_depth: int | None, residual: bool | None = None) -> Candidate:
    """Every dimension at ``pick`` (max or min) of its choices, with every exit the space allows
    (heads cost nothing to train along, and every head trains every step)."""
    depth = pick(space.head_depth) if head_depth is None else head_depth
    residual = pick(space.exit_residual) if residual is None else residual
    last = len(space.decoder_widths)
    return Candidate(
        encoder_blocks=pick(space.encoder_blocks), width_mult=pick(space.width_mult), ecu=pick(space.ecu),
        lidar_depth=pick(space.lidar_depth), lidar_width=pick(space.lidar_width), ecu_band=pick(space.ecu_band),
        ecu_width=pick(space.ecu_width), decoder_widths=tuple(pick(c) for c in space.decoder_widths),
        exits=tuple(sorted(set(space.optional_exits) | set(space.required_exits))) + (last,),
        head_depth=depth, head_width=pick(space.head_width) if depth == 2 else 0,
        encoder_exits=space.optional_encoder_exits, lidar_exit=True in space.lidar_exit,
        lidar_first=pick(space.lidar_first), exit_residual=residual,
        **{f: pick(getattr(space, f)) for f in HEAD_FIELDS})


def largest_candidate(space: SearchSpace, head_depth: int | None = None, residual: bool | None = None
                      ) -> Candidate:
    """The biggest network of ``space`` with every exit it allows."""
    return _extreme_candidate(space, max, head_depth, residual)


def smallest_candidate(space: SearchSpace, head_depth: int | None = None) -> Candidate:
    """The smallest backbone of ``space``, with every exit."""
    return _extreme_candidate(space, min, head_depth)


def random_training_subnet(space: SearchSpace, rng: random.Random) -> Candidate:
    """A random backbone of ``space`` (each dimension drawn uniformly) with every exit."""
    base = largest_candidate(space)
    ecu = rng.choice(space.ecu)
    depth = rng.choice(space.head_depth)
    residual = rng.choice(space.exit_residual)
    return dataclasses.replace(
        base, encoder_blocks=rng.choice(space.encoder_blocks), width_mult=rng.choice(space.width_mult), ecu=ecu,
        lidar_depth=rng.choice(space.lidar_depth) if ecu else 0, lidar_width=rng.choice(space.lidar_width) if ecu else 0,
        ecu_band=rng.choice(space.ecu_band) if ecu else 0, ecu_width=rng.choice(space.ecu_width) if ecu else 0,
        decoder_widths=tuple(rng.choice(c) for c in space.decoder_widths),
        head_depth=depth, head_width=rng.choice(space.head_width) if depth == 2 else 0,
        lidar_first=rng.choice(space.lidar_first), exit_residual=residual,
        # drawn only where the space sizes heads per position: other spaces draw what they drew before
        **{f: rng.choice(getattr(space, f)) for f in HEAD_FIELDS if getattr(space, f) != (0,)})


def _widest_heads(space: SearchSpace, depth: int) -> list[dict]:
    """Per-position heads of every depth the space offers there beside heads of ``depth`` layers, each at
    the widest width any head has: a head slot per position and depth, whose leading channels every
    narrower head of that slot is (Once-for-All style)."""
    wide = max([w for f in ("head_width", "encoder_head_width", "ecu_head_width") for w in getattr(space, f)])
    return [{"encoder_head_depth": e, "encoder_head_width": wide, "ecu_head_depth": c, "ecu_head_width": wide}
            for e in sorted({d or depth for d in space.encoder_head_depth})
            for c in sorted({d or depth for d in space.ecu_head_depth})]


def head_kinds(space: SearchSpace) -> list[tuple[int, bool]]:
    """Every kind of exit head set ``space`` has: (depth, residual)."""
    return [(d, r) for d in sorted(set(space.head_depth)) for r in sorted(set(space.exit_residual))]


def with_head_kind(candidate: Candidate, space: SearchSpace, depth: int, residual: bool) -> Candidate:
    """``candidate`` with exit heads of ``depth`` layers, correcting the scan or not (``residual``)."""
    return dataclasses.replace(candidate, head_depth=depth, exit_residual=residual,
                               head_width=max(space.head_width) if depth == 2 else 0)


class Supernet(nn.Module):
    def __init__(self, space: SearchSpace) -> None:
        super().__init__()
        self.space = space
        self.largest = largest_candidate(space)
        slots: dict[str, nn.Module] = {}
        for depth, residual in head_kinds(space):
            for heads in _widest_heads(space, depth):
                widest = dataclasses.replace(largest_candidate(space, depth, residual), **heads)
                # the whole image encoder in one slot; encoder exits split a candidate's encoder into views of it
                for spec in stage_specs(dataclasses.replace(widest, encoder_exits=())) + stage_specs(widest):
                    slot = slot_of(spec)
                    if slot not in slots and not (isinstance(spec.config, ImageEncoderConfig) and spec.config.start):
                        slots[slot] = spec.config.build()
        self.slots = nn.ModuleDict(slots)
        self.ecu_channels = ImageEncoderConfig(self.largest.encoder_blocks, self.largest.width_mult).out_channels()
        self._plans: OrderedDict[Candidate, tuple] = OrderedDict()
        self._stage_plans: dict[tuple[str, object], tuple[nn.Module, list[tuple]]] = {}
        self._tensors: dict[str, torch.Tensor] | None = None   # by name; see _named_tensors
        self._graph_stages: dict[tuple, tuple] = {}   # see _stage_function

    # -- candidates as views ------------------------------------------------------------------------
    def _check_contains(self, candidate: Candidate) -> None:
        # the weights do not depend on the precision a candidate is deployed at, nor on the size it works at
        as_searched = dataclasses.replace(candidate, precision=self.space.precision[0],
                                          downscale=self.space.downscale[0])
        if not self.space.contains(as_searched) and candidate != self.largest:
            raise UserError(f"candidate {candidate.key} is outside the supernet's space '{self.space.name}': "
                            "train a supernet for a space that contains it")

    @staticmethod
    def _stage_entries(spec: StageSpec, module: nn.Module) -> list[tuple]:
        """Per tensor of stage ``spec``'s ``module``: its key in a network, its name here, its stage,
        local name and shape."""
        return [(f"stages.{spec.name}.{local}", super_name(spec, local), spec, local, t.shape)
                for local, t in [*module.named_parameters(), *module.named_buffers()]]

    @classmethod
    def _entries(cls, network: AnytimeDepthNet) -> list[tuple]:
        """``_stage_entries`` of every stage of ``network``."""
        return [e for spec in network.specs for e in cls._stage_entries(spec, network.stages[spec.name])]

    def _plan(self, candidate: Candidate) -> tuple[AnytimeDepthNet, list[tuple]]:
        """A weightless (meta) network of ``candidate`` and, per tensor, where it lives here."""
        if candidate in self._plans:
            self._plans.move_to_end(candidate)
            return self._plans[candidate]
        self._check_contains(candidate)
        stages = {spec.name: self._stage_plan(spec) for spec in stage_specs(candidate)}
        template = AnytimeDepthNet(candidate, stages={name: module for name, (module, _) in stages.items()})
        plan = (template, [entry for _, entries in stages.values() for entry in entries])
        self._plans[candidate] = plan
        if len(self._plans) > 64:
            self._plans.popitem(last=False)
        return plan

    def _stage_plan(self, spec: StageSpec) -> tuple[nn.Module, list[tuple]]:
        """A weightless (meta) module of stage ``spec`` and its ``_stage_entries``, built once per stage name
        and config: a random subnet is mostly stages other subnets had, and building them took most of
        a step's host time (a GPU waited on it). Keyed by name too, so that no network holds one module
        twice (a parameter swap for one would then be the other's)."""
        key = (spec.name, spec.config)
        if key not in self._stage_plans:
            with torch.device("meta"):
                module = spec.config.build()
            self._stage_plans[key] = (module, self._stage_entries(spec, module))
        return self._stage_plans[key]

    def subnet_tensors(self, candidate: Candidate, entries: list[tuple] | None = None) -> dict[str, torch.Tensor]:
        """``candidate``'s parameters and buffers, as slices of this supernet's."""
        if entries is None:
            _, entries = self._plan(candidate)
        full = self._named_tensors()
        return {key: slice_of(spec, local, full[name], shape, self.ecu_channels)
                for key, name, spec, local, shape in entries}

    def _named_tensors(self) -> dict[str, torch.Tensor]:
        """This supernet's parameters and buffers by name, looked up once: training updates them in
        place, and only moving the module (``_apply``: ``to``, ``cuda``, ``float``) replaces them."""
        if self._tensors is None:
            self._tensors = {**dict(self.slots.named_parameters()), **dict(self.slots.named_buffers())}
        return self._tensors

    def _apply(self, fn, *args, **kwargs):
        self._tensors = None
        self._graph_stages = {}
        return super()._apply(fn, *args, **kwargs)

    def forward_subnet(self, candidate: Candidate, image: torch.Tensor, scan: torch.Tensor,
                       scan_row: int | None = None, graphs: StageGraphs | None = None) -> list[torch.Tensor]:
        """``candidate``'s forward pass on this supernet's weights (differentiable, no copies);
        ``graphs``: each stage replayed from its CUDA graph (``explorer.supernet._graphs``)."""
        template, _ = self._plan(candidate)
        for stage in template.stages.values():   # a stage module's mode is its children's: train() sets both
            if stage.training != self.training:
                stage.train(self.training)
        if graphs is not None:
            return template(image, scan, scan_row, call_stage=lambda *a: self._graphed_stage(graphs, *a))
        # tie_weights=False: a template holds no module twice (see _stage_plan), so there is nothing to
        # untie, and looking for it walked every module of the template at every call
        return functional_call(template, self.subnet_tensors(candidate), (image, scan, scan_row),
                               tie_weights=False)

    def _graphed_stage(self, graphs: StageGraphs, spec: StageSpec, module: nn.Module, args: list[torch.Tensor],
                       scan_row: int) -> list[torch.Tensor]:
        """Stage ``spec`` (its weightless ``module``) on ``args``, replayed from its graph in ``graphs``."""
        row = (scan_row,) if spec.uses_scan_row else ()
        if any(isinstance(r, torch.Tensor) for r in row):   # rows per column change with every batch: no graph
            return [module(*args, *row)]
        key = (spec.name, spec.config, row, module.training)
        if key not in self._graph_stages:
            self._graph_stages[key] = self._stage_function(spec, module, row)
        run, params, buffers = self._graph_stages[key]
        if not params:   # nothing to train (path 0 as a stage): a graph would save nothing worth its memory
            return [module(*args, *row)]
        return graphs.run(key, run, args, params, buffers)

    def _stage_function(self, spec: StageSpec, module: nn.Module, row: tuple) -> tuple:
        """(the function a graph of stage ``spec`` captures, the params it reads, the buffers it changes):
        looked up once per stage, as the graph itself is (a step runs some fifty stages)."""
        _, entries = self._stage_plan(spec)
        full = self._named_tensors()
        tensors = [full[name] for _, name, _, _, _ in entries]

        def run(*inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            views = {local: slice_of(spec, local, full[name], shape, self.ecu_channels)
                     for _, name, _, local, shape in entries}
            out = functional_call(module, views, (*inputs, *row), tie_weights=False)
            return out if isinstance(out, tuple) else (out,)
        return run, [t for t in tensors if t.requires_grad], [t for t in tensors if not t.requires_grad]

    def forward(self, image: torch.Tensor, scan: torch.Tensor, scan_row: int | None = None) -> list[torch.Tensor]:
        return self.forward_subnet(self.largest, image, scan, scan_row)

    def extract(self, candidate: Candidate) -> AnytimeDepthNet:
        """An ordinary network of ``candidate`` carrying copies of its slices of the supernet."""
        self._check_contains(candidate)
        # built where the supernet is: on a GPU, a network built on the CPU would copy each slice to the
        # host and back, two transfers (and a wait) per tensor
        with next(self.parameters()).device:
            net = build_network(candidate)
        # the network at hand says where its tensors live (a meta template would be a second build, as
        # long as this one on a CPU); load_state_dict copies, so the slices need no copy of their own
        entries = self._plans[candidate][1] if candidate in self._plans else self._entries(net)
        tensors = self.subnet_tensors(candidate, entries)
        with torch.no_grad():
            net.load_state_dict({k: tensors[k] for k in net.state_dict()})
        return net

    def stages_of(self, candidate: Candidate) -> list[StageSpec]:
        """``candidate``'s stages, in order (refused, in one clear line, outside this supernet's space)."""
        self._check_contains(candidate)
        return stage_specs(candidate)

    def extract_stage(self, spec: StageSpec) -> nn.Module:
        """Stage ``spec``'s module alone, carrying copies of its slices (as ``extract`` for a whole
        candidate): an evaluation that already has a candidate's other stages builds this one only."""
        with next(self.parameters()).device:   # as in extract
            module = spec.config.build()
        full = self._named_tensors()
        with torch.no_grad():   # load_state_dict copies
            module.load_state_dict({local: slice_of(spec, local, full[super_name(spec, local)], t.shape,
                                                    self.ecu_channels)
                                    for local, t in module.state_dict().items()})
        return module

    def extract_encoder(self, width_mult: float) -> ImageEncoder:
        """The whole image encoder (the space's deepest) at ``width_mult``, carrying copies of its
        slices: every candidate of that width runs a prefix of it, split at its exits."""
        if width_mult not in self.space.width_mult:
            raise ValueError(f"width {width_mult} is not one of the space's {self.space.width_mult}")
        return self.extract_stage(StageSpec("image_encoder", ImageEncoderConfig(self.largest.encoder_blocks, width_mult),
                                            ("image",), ("enc",)))
