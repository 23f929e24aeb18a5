"""ONNX graphs of a network's stages (and of the whole network), from the one torch definition.

Each stage becomes one graph whose inputs and outputs are the stage's named tensors, so running
the graphs in order reproduces ``AnytimeDepthNet.forward`` and every exit's depth map is available
as soon as its stage ends. Path 0 (the interpolated scan) is its own small graph.
"""

from __future__ import annotations

import io
import warnings

import torch
from torch import nn

from explorer.model.exits import interpolate_scan
from explorer.model.network import AnytimeDepthNet, StageSpec

OPSET = 17


class _Path0(nn.Module):
    def __init__(self, height: int) -> None:
        super().__init__()
        self.height = height

    def forward(self, scan: torch.Tensor) -> torch.Tensor:
        return interpolate_scan(scan, self.height)


class _Whole(nn.Module):
    def __init__(self, net: AnytimeDepthNet, scan_row: int) -> None:
        super().__init__()
        self.net, self.scan_row = net, scan_row

    def forward(self, image: torch.Tensor, scan: torch.Tensor):
        return tuple(self.net(image, scan, self.scan_row))


def _export(module: nn.Module, args: tuple, input_names: list[str], output_names: list[str]) -> bytes:
    # The exporter restores the wrapper's training flag on all its children afterwards: a fresh
    # wrapper is in training mode and would leave the network's BatchNorms training.
    module.eval()
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, buf, input_names=input_names, output_names=output_names,
                          opset_version=OPSET, dynamo=False, do_constant_folding=True)
    return buf.getvalue()


#: the input that carries each image column's scan row, in graphs exported with ``rows_input``
SCAN_ROWS = "scan_rows"


def example_inputs(input_size: tuple[int, int], batch: int = 1, rows_input: bool = False) -> dict[str, torch.Tensor]:
    """Random inputs at ``input_size``; with ``rows_input`` also ``scan_rows``, a line slanted across
    the middle third of the image (int64 (N, W))."""
    h, w = input_size
    g = torch.Generator().manual_seed(0)
    env = {"image": torch.rand(batch, 3, h, w, generator=g), "scan": torch.rand(batch, w, generator=g) * 5 + 0.5}
    if rows_input:
        line = torch.linspace(h / 3, 2 * h / 3, w).round().to(torch.int64).clamp(0, h - 1)
        env[SCAN_ROWS] = line.expand(batch, w).contiguous()
    return env


class _Segment(nn.Module):
    """Consecutive stages run as one graph (for deployment: fewer launches, same exits)."""

    def __init__(self, net: AnytimeDepthNet, specs: list[StageSpec], inputs: list[str], outputs: list[str],
                 scan_row: int) -> None:
        super().__init__()
        self.net, self.specs, self.inputs, self.outputs, self.scan_row = net, specs, inputs, outputs, scan_row

    def forward(self, *tensors: torch.Tensor):
        env = dict(zip(self.inputs, tensors))
        row = env.get(SCAN_ROWS, self.scan_row)   # each column's row, where the graph takes them
        for spec in self.specs:
            self.net.run_stage(spec, env, row)
        return tuple(env[n] for n in self.outputs)


def segments(specs: list[StageSpec]) -> list[list[StageSpec]]:
    """Stages grouped so that each group ends with an exit head: every exit's depth map is
    available as soon as its group ends, with as few graph launches as that allows."""
    groups, current = [], []
    for spec in specs:
        current.append(spec)
        if spec.path is not None:
            groups.append(current)
            current = []
    if current:
        groups.append(current)
    return groups


def _export_groups(net: AnytimeDepthNet, input_size: tuple[int, int], scan_row: int | None,
                   groups: list[list[StageSpec]], keep_all_outputs: bool,
                   rows_input: bool = False) -> list[tuple[dict, bytes]]:
    """Path 0's graph, then one graph per group of consecutive stages. A graph outputs what later
    groups read and its depth maps (or everything its stages write, with ``keep_all_outputs``). With
    ``rows_input`` the groups that crop the scan's band take each column's row (``scan_rows``)."""
    net = net.eval()
    h, _ = input_size
    scan_row = h // 2 if scan_row is None else scan_row
    env = example_inputs(input_size, rows_input=rows_input)
    row = env.get(SCAN_ROWS, scan_row)
    out = [({"name": "path0", "stages": [], "inputs": ["scan"], "outputs": ["depth_0"], "path": 0},
            _export(_Path0(h), (env["scan"],), ["scan"], ["depth_0"]))]
    with torch.no_grad():
        for gi, group in enumerate(groups):
            produced = [o for sp in group for o in sp.outputs]
            needed_later = {i for later in groups[gi + 1:] for sp in later for i in sp.inputs}
            inputs = list(dict.fromkeys(i for sp in group for i in sp.inputs if i not in produced))
            if rows_input and any(sp.uses_scan_row for sp in group):
                inputs.append(SCAN_ROWS)
            outputs = [o for o in produced if keep_all_outputs or o in needed_later or o.startswith("depth_")]
            graph = _export(_Segment(net, group, inputs, outputs, scan_row), tuple(env[n] for n in inputs),
                            inputs, outputs)
            for sp in group:
                net.run_stage(sp, env, row)
            out.append(({"name": "+".join(sp.name for sp in group), "stages": [sp.name for sp in group],
                         "inputs": inputs, "outputs": outputs, "path": group[-1].path}, graph))
    return out


def export_stages(net: AnytimeDepthNet, input_size: tuple[int, int], scan_row: int | None = None
                  ) -> list[tuple[StageSpec | None, bytes]]:
    """[(None, path-0 graph), (spec, stage graph), ...]: one graph per stage, in execution order
    (what measurement and calibration time)."""
    graphs = _export_groups(net, input_size, scan_row, [[sp] for sp in net.specs], keep_all_outputs=True)
    return [(None, graphs[0][1])] + [(sp, g) for sp, (_, g) in zip(net.specs, graphs[1:])]


def export_segments(net: AnytimeDepthNet, input_size: tuple[int, int], scan_row: int | None = None,
                    rows_input: bool = False) -> list[tuple[dict, bytes]]:
    """[(description, graph), ...] for deployment: path 0, then one graph per group of stages ending
    with an exit. A description has name, stages, inputs, outputs and the path it completes. With
    ``rows_input`` the scan's row per column is an input (``scan_rows``), for a slanted scan line."""
    return _export_groups(net, input_size, scan_row, segments(net.specs), keep_all_outputs=False,
                          rows_input=rows_input)


def export_whole(net: AnytimeDepthNet, input_size: tuple[int, int], scan_row: int | None = None) -> bytes:
    """The whole network as one graph (outputs depth_0..depth_K), to compare with staged runs."""
    net = net.eval()
    scan_row = input_size[0] // 2 if scan_row is None else scan_row
    env = example_inputs(input_size)
    names = [f"depth_{i}" for i in range(net.candidate.num_paths)]
    with torch.no_grad():
        return _export(_Whole(net, scan_row), (env["image"], env["scan"]), ["image", "scan"], names)
