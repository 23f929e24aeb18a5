"""A small pose network for self-supervised training (MonoDepth2's idea, much smaller): two frames
in, the rigid transform from the first camera to the second out. Used only during training; the
depth network the search costs and exports never contains it."""

from __future__ import annotations

import torch
from torch import nn

#: MonoDepth2 scales the raw outputs by 0.01 so that training starts near the identity.
OUTPUT_SCALE = 0.01


class PoseNet(nn.Module):
    """``forward(target, source)`` -> (N, 4, 4) transform from target-camera to source-camera
    coordinates. Images are (N, 3, H, W) in [0, 1]."""

    def __init__(self, widths: tuple[int, ...] = (16, 32, 64, 128, 128)) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 6
        for w in widths:
            layers += [nn.Conv2d(cin, w, 3, stride=2, padding=1), nn.ReLU(inplace=True)]
            cin = w
        self.features = nn.Sequential(*layers)
        self.head = nn.Conv2d(cin, 6, 1)

    def forward(self, target: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        x = self.head(self.features(torch.cat([target, source], dim=1) - 0.45))
        motion = OUTPUT_SCALE * x.mean(dim=(2, 3))
        return transform_from_parameters(motion[:, :3], motion[:, 3:])


def transform_from_parameters(axis_angle: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(N, 4, 4) rigid transforms from axis-angle rotations (N, 3) and translations (N, 3) (Rodrigues)."""
    angle = axis_angle.norm(dim=1, keepdim=True).clamp(min=1e-8)
    axis = axis_angle / angle
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=1).view(-1, 3, 3)
    eye = torch.eye(3, device=axis.device, dtype=axis.dtype).expand_as(skew)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    rotation = eye + s * skew + (1 - c) * skew @ skew
    out = torch.eye(4, device=axis.device, dtype=axis.dtype).repeat(axis.shape[0], 1, 1)
    out[:, :3, :3] = rotation
    out[:, :3, 3] = translation
    return out
