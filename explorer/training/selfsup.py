"""Self-supervised training loss from video (MonoDepth2, Godard et al. 2019), with metric scale from
the 2D LiDAR.

For every exit's depth map, each neighbouring frame is warped into the target view with the depth
and the relative pose (from :class:`explorer.training.pose_net.PoseNet` trained jointly, or given by the
data); the photometric error is 0.85 * (1 - SSIM) / 2 + 0.15 * L1; the per-pixel minimum over the
source frames handles occlusions; auto-masking drops pixels whose error is already lower without
warping (static camera, objects moving with it); an edge-aware smoothness term acts on the
mean-normalised disparity. Monocular video fixes depth only up to scale: an L1 term on the scan
row's valid returns gives it metres. Without that term (and without given poses), evaluation
needs MonoDepth2's per-image median scaling.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from explorer.errors import UserError
from explorer.training.pose_net import PoseNet

SUPERVISIONS = ("supervised", "self", "mixed")
POSE_SOURCES = ("net", "given")
SSIM_WEIGHT = 0.85
SMOOTHNESS_WEIGHT = 1e-3
#: Weight of the scan term (metres of L1) against the photometric error (about 0.1 at the start).
SCAN_WEIGHT = 0.1
#: Depths below this are clamped before warping (the linear exit heads can predict any value).
MIN_DEPTH = 0.1


def ssim_dissimilarity(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(1 - SSIM) / 2 per pixel over 3x3 windows, reflection-padded (MonoDepth2's), in [0, 1]."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x, y = F.pad(x, (1, 1, 1, 1), mode="reflect"), F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = F.avg_pool2d(x, 3, 1), F.avg_pool2d(y, 3, 1)
    sigma_x = F.avg_pool2d(x * x, 3, 1) - mu_x ** 2
    sigma_y = F.avg_pool2d(y * y, 3, 1) - mu_y ** 2
    sigma_xy = F.avg_pool2d(x * y, 3, 1) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sigma_x + sigma_y + c2)
    return torch.clamp((1 - num / den) / 2, 0, 1)


def photometric_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N, 1, H, W): 0.85 * SSIM dissimilarity + 0.15 * L1, averaged over the colour channels."""
    l1 = (pred - target).abs().mean(1, keepdim=True)
    return SSIM_WEIGHT * ssim_dissimilarity(pred, target).mean(1, keepdim=True) + (1 - SSIM_WEIGHT) * l1


def warp(source: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, target_to_source: torch.Tensor
         ) -> torch.Tensor:
    """The source frame seen from the target camera: each target pixel is lifted to 3D with its
    ``depth`` (N, 1, H, W), moved by ``target_to_source`` (N, 4, 4) and projected with ``K``
    (N, 3, 3, pixel-index coordinates); ``source`` is sampled there (bilinear, border padding)."""
    n, _, h, w = depth.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=depth.device, dtype=depth.dtype),
                            torch.arange(w, device=depth.device, dtype=depth.dtype), indexing="ij")
    pixels = torch.stack([xs, ys, torch.ones_like(xs)]).view(1, 3, -1)
    points = torch.linalg.inv(K) @ pixels * depth.view(n, 1, -1)
    moved = target_to_source[:, :3, :3] @ points + target_to_source[:, :3, 3:]
    projected = K @ moved
    uv = projected[:, :2] / projected[:, 2:].clamp(min=1e-3)
    grid = torch.stack([2 * uv[:, 0] / max(w - 1, 1) - 1, 2 * uv[:, 1] / max(h - 1, 1) - 1], dim=-1)
    return F.grid_sample(source, grid.view(n, h, w, 2), mode="bilinear", padding_mode="border",
                         align_corners=True)


def min_reprojection(target: torch.Tensor, warped: list[torch.Tensor]) -> torch.Tensor:
    """Per-pixel minimum over the warped sources of the photometric error, (N, 1, H, W)."""
    return torch.cat([photometric_error(w, target) for w in warped], dim=1).min(dim=1, keepdim=True).values


def reprojection_loss(target: torch.Tensor, sources: list[torch.Tensor], warped: list[torch.Tensor],
                      automask: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """(per-pixel loss (N, 1, H, W), mask of the pixels the warping explains) with MonoDepth2's
    per-pixel minimum over sources and auto-masking: a pixel whose unwarped source already matches
    better (a static scene, or something moving with the camera) is left out."""
    best = min_reprojection(target, warped)
    if not automask:
        return best, torch.ones_like(best, dtype=torch.bool)
    identity = torch.cat([photometric_error(s, target) for s in sources], dim=1)
    # a tiny noise breaks ties in favour of neither (MonoDepth2 does the same)
    identity = identity + torch.randn_like(identity) * 1e-5
    still, _ = identity.min(dim=1, keepdim=True)
    mask = best < still
    return torch.where(mask, best, still), mask


def photometric_score(depth: torch.Tensor, batch: dict) -> torch.Tensor:
    """Per frame (N,): how well ``depth`` (N, 1, H, W), warped with the batch's given poses, explains the
    target from its neighbours: the mean over pixels of MonoDepth2's per-pixel minimum reprojection
    error, each pixel's error capped by that of the unwarped neighbours (auto-masking, without the
    training's random tie-break). It scores depth maps where no depth was recorded; lower is better,
    and a depth off in scale warps to the wrong place, so the scale counts too."""
    target, K = batch["image"], batch["K"]
    sources = [batch["sources"][:, k] for k in range(2)]
    poses = [batch["pose"][:, k] for k in range(2)]
    depth = depth.clamp(min=MIN_DEPTH)
    best = min_reprojection(target, [warp(s, depth, K, p) for s, p in zip(sources, poses)])
    still = torch.cat([photometric_error(s, target) for s in sources], dim=1).min(dim=1, keepdim=True).values
    return torch.minimum(best, still).mean(dim=(1, 2, 3))


def smoothness(depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of the mean-normalised disparity (gradients weighted by exp(-|dI|))."""
    disp = 1.0 / depth
    disp = disp / disp.mean(dim=(2, 3), keepdim=True).clamp(min=1e-7)
    dx, dy = (disp[..., :, :-1] - disp[..., :, 1:]).abs(), (disp[..., :-1, :] - disp[..., 1:, :]).abs()
    ix = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    iy = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()


def scan_l1(depth: torch.Tensor, scan: torch.Tensor, row: "int | torch.Tensor") -> torch.Tensor:
    """Mean |depth - scan| over the scan's valid returns (scan > 0), metres, each return on ``row`` or
    on its column's own row (an integer tensor (N, W))."""
    valid = scan > 0
    if not bool(valid.any()):
        return depth.sum() * 0.0
    if isinstance(row, torch.Tensor):
        on_line = depth[:, 0].gather(1, row.to(depth.device, torch.int64)[:, None, :]).squeeze(1)
    else:
        on_line = depth[:, 0, row, :]
    return ((on_line - scan).abs() * valid).sum() / valid.sum()


class SelfSupervisedLoss(nn.Module):
    """The per-exit self-supervised loss; holds the pose network when poses are learned (its
    parameters train with the depth network's)."""

    def __init__(self, poses: str = "net", scan_loss: bool = True) -> None:
        super().__init__()
        if poses not in POSE_SOURCES:
            raise UserError(f"poses '{poses}': use one of {', '.join(POSE_SOURCES)}")
        self.poses, self.scan_loss = poses, scan_loss
        self.pose_net = PoseNet() if poses == "net" else None

    def relative_poses(self, batch: dict) -> list[torch.Tensor]:
        """Target-to-source transforms for the two neighbours."""
        if self.pose_net is None:
            if not bool(torch.as_tensor(batch["pose_known"]).all()):
                raise UserError("--poses given: this data has no poses (KITTI needs oxts/ and "
                                "calib_imu_to_velo.txt, a folder poses.txt); use --poses net")
            return [batch["pose"][:, k] for k in range(2)]
        return [self.pose_net(batch["image"], batch["sources"][:, k]) for k in range(2)]

    def forward(self, outputs: list[torch.Tensor], batch: dict, row: "int | torch.Tensor",
                weights: tuple[float, ...] | None = None) -> tuple[torch.Tensor, list[float]]:
        """Weighted mean over the exits (``outputs[1:]``; path 0 has no parameters) and each exit's
        loss. ``batch`` holds image, sources, K, pose, pose_known and scan on the loss's device, and
        ``hint`` when training with depth hints."""
        target, K = batch["image"], batch["K"]
        sources = [batch["sources"][:, k] for k in range(2)]
        poses = self.relative_poses(batch)
        hint = batch.get("hint")
        if hint is not None:  # see explorer.training.depth_hints
            with torch.no_grad():
                hint_error = min_reprojection(target, [warp(s, hint, K, p) for s, p in zip(sources, poses)])
        losses = []
        for depth in outputs[1:]:
            depth = depth.clamp(min=MIN_DEPTH)
            warped = [warp(s, depth, K, p) for s, p in zip(sources, poses)]
            per_pixel, _ = reprojection_loss(target, sources, warped)
            loss = per_pixel.mean() + SMOOTHNESS_WEIGHT * smoothness(depth, target)
            if hint is not None:
                depth_error = min_reprojection(target, warped).detach()
                loss = loss + hint_loss(depth, hint, depth_error, hint_error)
            if self.scan_loss:
                loss = loss + SCAN_WEIGHT * scan_l1(depth, batch["scan"], row)
            losses.append(loss)
        w = weights or (1.0,) * len(losses)
        if len(w) != len(losses):
            raise UserError(f"exit_weights has {len(w)} values but the network has {len(losses)} exits")
        total = sum(wi * li for wi, li in zip(w, losses)) / sum(w)
        return total, [float(li.detach()) for li in losses]


def hint_loss(depth: torch.Tensor, hint: torch.Tensor, depth_error: torch.Tensor,
              hint_error: torch.Tensor) -> torch.Tensor:
    """Depth Hints' supervised term: ``log(1 + |depth - hint|)`` where the hint's photometric error is
    lower than the prediction's, averaged over all pixels."""
    use = (hint_error < depth_error).to(depth.dtype)
    return (torch.log1p((depth - hint).abs()) * use).mean()
