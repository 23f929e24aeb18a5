"""Exit heads refitted to a candidate: the output layer of each head, least squares on the calibration frames.

A supernet's exit head (at one position, of one kind) is shared by every candidate that has it, whatever
decoder feeds it: its output layer fits the average of those decoders, and a candidate whose features
differ from that average is estimated worse than it trains. Stand-alone, the last exit of plain-head
candidates came out better than the exit before it; estimated from a 600-step supernet, it came out worse
(RMSE 0.41 against 0.32 on one candidate), and 100 steps of training its head alone (17 weights) brought it
back to 0.31. The output layer is linear, and what follows it (nearest and bilinear up-sampling, the scan a
residual head corrects) is linear, per channel and keeps constants, so its best weights for a candidate
are a least-squares fit: the features the layer reads, brought to the output's size, against the depth
(less the scan for a residual head), over the calibration frames' pixels with depth. Like BatchNorm
recalibration, it uses training frames only and changes no weight another candidate reads.
"""

from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache

import torch

from explorer.model.exits import ExitHead
from explorer.model.ops import Resize

#: ridge weight, relative to the mean diagonal of the normal equations, pulling the fit towards the
#: supernet's weights where the features barely vary (a channel a ReLU keeps at zero, say)
RIDGE = 1e-4

#: output layers reading more channels keep the supernet's weights: a depth-1 head on the encoder or the
#: first decoder stages reads hundreds of channels at a coarse stride, where the calibration frames hold
#: few more distinct feature vectors than the layer has weights (a fit would follow their noise), and
#: solving for them would cost more than the rest of the evaluation
MAX_CHANNELS = 64

#: the fit reads every this-many-th calibration frame: with about 256 pixels each, tens of thousands of
#: rows for at most 65 weights, at a quarter of the cost (spread over the set: its first frames alone,
#: consecutive ones of a few scenes, fitted the heads worse than no refit)
FRAME_STEP = 4


class HeadRefit:
    """The normal equations of ``head``'s output layer, accumulated batch by batch (float64), then solved."""

    def __init__(self, head: ExitHead) -> None:
        self.head = head
        self.layer = head.layers[-1]
        self.active = self.layer.in_channels <= MAX_CHANNELS
        n = self.layer.in_channels + 1
        self.gram = torch.zeros(n, n, dtype=torch.float64)
        self.rhs = torch.zeros(n, dtype=torch.float64)

    def add(self, args: tuple[torch.Tensor, ...], depth: torch.Tensor) -> None:
        """One batch: the head's inputs ``args`` (as its forward takes them) and the depth (N, 1, H, W)
        its output should give (0: no depth)."""
        if not self.active:
            return
        args, depth = tuple(a[::FRAME_STEP] for a in args), depth[::FRAME_STEP]
        with torch.no_grad():
            rows_at, cols_at = _grid(depth.shape[2]), _grid(depth.shape[3])
            basis, scan = self._basis(rows_at, cols_at, *args)
            depth = depth.to(basis.device)[:, 0][:, rows_at][:, :, cols_at]
            target = depth if scan is None else depth - scan
            valid = depth > 0
            rows = basis.permute(0, 2, 3, 1)[valid].double()
            rows = torch.cat([rows, torch.ones(len(rows), 1, dtype=rows.dtype, device=rows.device)], 1)
            self.gram += (rows.T @ rows).cpu()
            self.rhs += (rows.T @ target[valid].double()).cpu()

    def _basis(self, rows_at: slice, cols_at: slice, x: torch.Tensor, *extra: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """What the output layer reads, per channel up-sampled as its output would be, at the output
        pixels ``rows_at`` x ``cols_at`` only, and the scan a residual head adds there (None for a plain
        one): ``ExitHead.forward`` up to its output layer."""
        head = self.head
        if head.config.lidar_channels:
            x = head.add(x, head.fuse(extra[0]).unsqueeze(2))
        features = head.layers[:-1](x)
        up_rows = _upsampling(head, features.shape[2], "rows", features)[rows_at]
        up_cols = _upsampling(head, features.shape[3], "cols", features)[cols_at]
        basis = up_rows @ features.contiguous() @ up_cols.T
        scan = extra[-1][:, 0][:, rows_at][:, :, cols_at] if head.config.residual else None
        return basis, scan

    def apply(self) -> None:
        """Sets the output layer to the fit (left as it is without a pixel with depth, or too wide)."""
        if not self.active or self.gram[-1, -1] == 0:
            return
        layer = self.layer
        current = torch.cat([layer.weight.detach().flatten(), layer.bias.detach()]).double().cpu()
        ridge = RIDGE * self.gram.diagonal().mean()
        eye = torch.eye(len(current), dtype=torch.float64)
        solution = torch.linalg.solve(self.gram + ridge * eye, self.rhs + ridge * current)
        with torch.no_grad():
            layer.weight.copy_(solution[:-1].view_as(layer.weight))
            layer.bias.fill_(float(solution[-1]))


#: the fit reads about this many pixels per frame and side (a regular grid): enough for a few dozen
#: weights over hundreds of frames, and the output's every pixel would make the refit cost more than
#: the rest of an evaluation
GRID = 16


def _grid(size: int) -> slice:
    """The rows (or columns) of an output of ``size`` the fit reads: every k-th, about ``GRID`` of them."""
    step = max(1, size // GRID)
    return slice(step // 2, None, step)


def _upsampling(head: ExitHead, size: int, axis: str, like: torch.Tensor) -> torch.Tensor:
    """The head's up-sampling (nearest, then bilinear) along one axis as a matrix (output x ``size``)."""
    return _upsampling_matrix(size, head.nearest.factor, head.resize.factor, head.resize.products, axis,
                              like.dtype, like.device)


@lru_cache(maxsize=256)
def _upsampling_matrix(size: int, nearest: int, bilinear: int, products: bool, axis: str, dtype: torch.dtype,
                       device: torch.device) -> torch.Tensor:
    """Up-sampling is separable: a constant row (or column) up-samples to the matrix's rows times a
    constant, so up-sampling the unit rows (columns) gives the matrix."""
    eye = torch.eye(size, dtype=dtype, device=device)
    probe = eye.view(size, 1, size, 1) if axis == "rows" else eye.view(size, 1, 1, size)
    out = Resize(bilinear, "bilinear", products)(Resize(nearest, "nearest")(probe))
    return (out[:, 0, :, 0] if axis == "rows" else out[:, 0, 0, :]).T


@contextmanager
def recording_head_inputs(net: torch.nn.Module):
    """Records, while the context runs ``net``, every exit head's inputs per call: {head: [args, ...]}.
    A refit takes the heads' inputs as BatchNorm recalibration made them (training mode, as the
    stage-by-stage evaluation keeps them), and fits each head once its own statistics are recalibrated."""
    record: dict[ExitHead, list[tuple]] = {}
    heads = [m for m in net.modules() if isinstance(m, ExitHead)]
    hooks = [h.register_forward_pre_hook(lambda m, args: record.setdefault(m, []).append(args)) for h in heads]
    try:
        yield record
    finally:
        for hook in hooks:
            hook.remove()


def refit_recorded(record: dict[ExitHead, list[tuple]], depths: list[torch.Tensor]) -> None:
    """Refits every head of ``record`` (see :func:`recording_head_inputs`) to ``depths``, one per call."""
    for head, calls in record.items():
        fit = HeadRefit(head)
        for args, depth in zip(calls, depths):
            fit.add(args, depth)
        fit.apply()
