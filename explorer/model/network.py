"""The anytime network: an ordered list of stages. Path i is ready once every stage up to and
including exit head i has run; the same list drives training, costing, export and the runtime."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Hashable, Mapping, Sequence

import torch
from torch import nn

from explorer.model.decoder import DecoderStageConfig
from explorer.model.downscale import DownscaleConfig
from explorer.model.ecu import ECUConfig
from explorer.model.exits import ExitHeadConfig, ScanFillConfig, interpolate_scan
from explorer.model.image_encoder import ImageEncoderConfig
from explorer.model.lidar_encoder import LidarEncoderConfig
from explorer.model.lidar_exit import LidarExitConfig
from explorer.space import MOBILENET_V1_BLOCKS, Candidate, encoder_stride


@dataclass(frozen=True)
class StageSpec:
    """One stage: its module's config (hashable, builds the module), the named tensors it reads and
    writes, and for an exit head the path it completes."""

    name: str
    config: Hashable
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    path: int | None = None

    @property
    def uses_scan_row(self) -> bool:
        return isinstance(self.config, ECUConfig)


def _encoder_tensor(block: int, encoder_blocks: int) -> str:
    """The name of the image feature after ``block`` blocks: a skip name when the decoder reads it."""
    if block < encoder_blocks and MOBILENET_V1_BLOCKS[block][2] == 2:
        return f"skip_s{encoder_stride(block)}"
    return f"enc_b{block}"


def stage_specs(candidate: Candidate, paper_graph: bool = False) -> list[StageSpec]:
    """The execution order of ``candidate``'s stages (path 0 needs none): the interpolated scan as
    a tensor when the exits correct it, the LiDAR-only exit, the LiDAR encoder when it runs first,
    the image encoder (split by its exits), the LiDAR encoder otherwise, the ECU, then decoder
    stages, each exit head right after what it reads. The last decoder stage leaves its up-sampling
    to its exit head where that gives the same values (``explorer.model.decoder``), and exit heads
    up-sample bilinearly as two matrix products (``ops.Resize``); ``paper_graph``: neither, the graph
    the paper measured, for its figures (the same parameters, the same values to float rounding).
    Residual exits read last the depth map they correct, the scan (``scan_fill``). A network working below
    its input size first resizes it (``downscale``), read by every later stage; its heads resize back."""
    stride, factor = candidate.working_stride, candidate.downscale
    image, scan = ("image_low", "scan_low") if factor > 1 else ("image", "scan")
    specs: list[StageSpec] = []
    path = 1
    residual = candidate.exit_residual
    base = ("scan_fill",) if residual else ()

    def add_exit(name: str, cfg: ExitHeadConfig | LidarExitConfig, inputs: tuple[str, ...]) -> None:
        nonlocal path
        specs.append(StageSpec(name, cfg, inputs + base, (f"depth_{path}",), path))
        path += 1

    if residual:
        specs.append(StageSpec("scan_fill", ScanFillConfig(), ("scan", "image"), ("scan_fill",)))
    if candidate.lidar_exit:
        add_exit("lidar_exit", LidarExitConfig(residual=residual), ("scan", "image"))
    if factor > 1:
        specs.append(StageSpec("downscale", DownscaleConfig(factor), ("image", "scan"), (image, scan)))
    lidar = None
    if candidate.ecu:
        taps = tuple(encoder_stride(k) for k in candidate.encoder_exits) if candidate.lidar_first else ()
        lidar = LidarEncoderConfig(candidate.lidar_depth, candidate.lidar_width, stride, taps)
        lidar_stage = StageSpec("lidar_encoder", lidar, (scan,), ("lidar", *(f"lidar_s{t}" for t in taps)))
        if candidate.lidar_first:
            specs.append(lidar_stage)
    start, x = 0, image
    for k in (*candidate.encoder_exits, candidate.encoder_blocks):
        seg = ImageEncoderConfig(k, candidate.width_mult, start)
        out = "enc" if k == candidate.encoder_blocks else _encoder_tensor(k, candidate.encoder_blocks)
        name = "image_encoder" if start == 0 else f"image_encoder_{start + 1}"
        specs.append(StageSpec(name, seg, (x,), (out, *(f"skip_s{s}" for s in sorted(seg.skip_strides(), reverse=True)))))
        if k < candidate.encoder_blocks:
            s = encoder_stride(k)
            fuse = lidar.tap_channels(s) if candidate.lidar_first else 0
            cfg = ExitHeadConfig(seg.out_channels(), *candidate.head("encoder"), s * factor, fuse, residual)
            add_exit(f"exit_b{k}", cfg, (out, f"lidar_s{s}") if fuse else (out,))
        start, x = k, out
    enc = ImageEncoderConfig(candidate.encoder_blocks, candidate.width_mult)
    skips = sorted(enc.skip_strides(), reverse=True)
    x = "enc"
    if candidate.ecu:
        if not candidate.lidar_first:
            specs.append(lidar_stage)
        # the scan's row is the input's: its feature row is found at the stride relative to the input
        ecu = ECUConfig(enc.out_channels(), lidar.out_channels(), candidate.ecu_band,
                        candidate.ecu_width, stride * factor)
        specs.append(StageSpec("ecu", ecu, ("enc", "lidar"), ("x0",)))
        x = "x0"
    channels = enc.out_channels()

    def exit_cfg(cin: int, scale: int, position: str = "decoder") -> ExitHeadConfig:
        return ExitHeadConfig(cin, *candidate.head(position), scale * factor, residual=residual,
                              bilinear_products=not paper_graph)

    if 0 in candidate.exits:
        add_exit("exit_0", exit_cfg(channels, stride, "ecu"), (x,))
    last = len(candidate.decoder_widths)
    for k, width in enumerate(candidate.decoder_widths, start=1):
        out_stride = stride // 2 ** k
        has_skip = out_stride in skips
        # the last stage's output feeds its exit head alone: the head up-samples after its 1x1 layers
        deferred = not paper_graph and k == last and not has_skip and k in candidate.exits
        cfg = DecoderStageConfig(channels, width, has_skip, upsample=not deferred)
        inputs = (x, f"skip_s{out_stride}") if has_skip else (x,)
        x, channels = f"x{k}", width
        specs.append(StageSpec(f"decoder_{k}", cfg, inputs, (x,)))
        if k in candidate.exits:
            head = exit_cfg(channels, out_stride)
            add_exit(f"exit_{k}", replace(head, nearest=2) if deferred else head, (x,))
    return specs


#: the scan's image row, or each image column's (an integer tensor (N, W)) where the line is slanted
ScanRow = "int | torch.Tensor"
#: runs a stage in its module's place: (spec, module, tensor inputs, scan row) -> outputs
StageCall = Callable[[StageSpec, nn.Module, list[torch.Tensor], ScanRow], Sequence[torch.Tensor]]


class AnytimeDepthNet(nn.Module):
    """``forward(image, scan, scan_row=None)`` returns the depth maps of paths 0..K, each
    (N, 1, H, W) metres. ``image`` is (N, 3, H, W) RGB in [0, 1], H and W divisible by the stride;
    ``scan`` is (N, W) metres (0 = no return) lying on image row ``scan_row`` (default H // 2), or on
    each column's own row (``scan_row`` an integer tensor (N, W): a tilted or offset LiDAR's line)."""

    def __init__(self, candidate: Candidate, paper_graph: bool = False,
                 stages: Mapping[str, nn.Module] | None = None) -> None:
        """``stages``: the stage modules by name where they are built already (a supernet's weightless
        templates, shared by the candidates that have the stage); the others are built here."""
        super().__init__()
        self.candidate = candidate
        self.specs = stage_specs(candidate, paper_graph)
        stages = stages or {}
        self.stages = nn.ModuleDict({s.name: stages[s.name] if s.name in stages else s.config.build()
                                     for s in self.specs})

    @property
    def stride(self) -> int:
        return self.candidate.stride

    def check_input(self, image: torch.Tensor, scan: torch.Tensor) -> None:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be (N, 3, H, W), got {tuple(image.shape)}")
        h, w = image.shape[2:]
        if h % self.stride or w % self.stride:
            raise ValueError(f"image sides {h}x{w} must divide by the encoder stride {self.stride}")
        if scan.shape != (image.shape[0], w):
            raise ValueError(f"scan must be (N, W) = ({image.shape[0]}, {w}), got {tuple(scan.shape)}")

    def run_stage(self, spec: StageSpec, env: dict[str, torch.Tensor], scan_row: ScanRow,
                  call_stage: StageCall | None = None) -> None:
        args = [env[name] for name in spec.inputs]
        if call_stage is not None:
            outs = tuple(call_stage(spec, self.stages[spec.name], args, scan_row))
        else:
            out = self.stages[spec.name](*args, *((scan_row,) if spec.uses_scan_row else ()))
            outs = out if isinstance(out, tuple) else (out,)
        env.update(zip(spec.outputs, outs))

    def forward(self, image: torch.Tensor, scan: torch.Tensor, scan_row: ScanRow | None = None,
                call_stage: StageCall | None = None) -> list[torch.Tensor]:
        """``call_stage(spec, module, tensor inputs, scan_row)``, where given, runs each stage in the
        module's place and returns its outputs as a sequence (a supernet's CUDA graphs do)."""
        self.check_input(image, scan)
        if scan_row is None:
            scan_row = image.shape[2] // 2
        elif isinstance(scan_row, torch.Tensor) and scan_row.dim() == 2:
            if scan_row.shape != scan.shape:
                raise ValueError(f"per-column scan rows must be (N, W) = {tuple(scan.shape)}, got "
                                 f"{tuple(scan_row.shape)}")
        else:
            scan_row = int(scan_row)
        env: dict[str, torch.Tensor] = {"image": image, "scan": scan}
        depths = [interpolate_scan(scan, image.shape[2])]
        for spec in self.specs:
            self.run_stage(spec, env, scan_row, call_stage)
            if spec.path is not None:
                depths.append(env[spec.outputs[0]])
        return depths


def build_network(candidate: Candidate, paper_graph: bool = False) -> AnytimeDepthNet:
    """The PyTorch network of ``candidate`` (randomly initialised); ``paper_graph``: the graph the paper
    measured (``stage_specs``), with the same parameters."""
    return AnytimeDepthNet(candidate, paper_graph)
