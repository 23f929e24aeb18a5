"""The paper's reference networks, in torch, one definition each, costed by the same tracer as the
candidates: FastDepth (full and NetAdapt-pruned), sparse-to-dense (Ma & Karaman; RGB + sparse depth,
ResNet-50 / ResNet-18 encoder) and MonoDepth2's ResNet-18 depth network.

Every layer whose cost matters is an ``nn`` layer or an ``explorer.model.ops`` module, so the
workload tracer (``explorer.cost.workloads``) sees it; ReLU/ELU/sigmoid are folded into the layer
before them as a deployment runtime does.

Decoders, checked against the paper's parameter counts (Tables 1 and 3):

- S2D: the paper's 28.39 M (ResNet-50, NYU) and 11.49 M (ResNet-18, KITTI) are exactly Ma &
  Karaman's network with its ``deconv2`` decoder (four 2x2 stride-2 transposed convolutions halving
  the channels), which is what ``s2d-resnet50`` / ``s2d-resnet18`` build. Their UpProj decoder
  (Laina et al.'s up-projection, 63.6 M with ResNet-50) is ``s2d-resnet50-upproj`` /
  ``s2d-resnet18-upproj``; it cannot be what the paper measured (its parameters are 2.2x the
  paper's). The un-pooling of UpProj is a nearest x2 resize here (same tensor sizes and traffic).
- MonoDepth2: ResNet-18 encoder (11.18 M) + its depth decoder (3.15 M) = 14.33 M; the paper says
  15.24 M (-6%, within 10%; the paper likely counts the encoder's unused ImageNet classifier).
- FastDepth 3.96 M (paper 4.016 M, -1.4%); pruned 1.36 M (fast-depth's 1.34 M, +1.6%).

GFLOPs (``explorer profile NAME --input-size HxW`` gives our exact MACs): the paper's "GFlops" column is
multiply-adds, with transposed convolutions counted as FLOP counters such as thop count them: as
the convolution over the zero-dilated input they are computed as (every output value x input
channels x kernel), 4x their real multiply-adds for sparse-to-dense's 2x2 stride-2 layers
(``explorer.cost.workloads.dilated_count_macs``; ``explorer profile`` shows it as ``macs_dilated``).
Counted so: S2D-ResNet-50 at 228x304 8.87 G vs 8.910 (-0.4%; real multiply-adds 6.86 G), S2D-ResNet-18
at 228x912 8.57 G vs 8.593 (-0.3%; real 8.20 G). MonoDepth2 at 192x640: 8.01 G vs 8.051 (-0.5%);
pruned FastDepth 0.366 G vs fast-depth's 0.37. One is off by more than 10%, and explained:
FastDepth's 0.737 G (-15%) is what FastDepth's own paper says (0.74 GMACs), so the 0.867 counts
something beyond its multiply-adds. Tests check our counts against ``torch.utils.flop_counter``
exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from explorer.errors import UserError
from explorer.model.exits import interpolate_scan
from explorer.model.ops import Concat, Resize, SkipAdd, conv_bn_relu

# -- FastDepth -------------------------------------------------------------------------------------
#: MobileNet v1 blocks (out channels, stride) after the first 3x3/2 convolution.
MOBILENET_V1 = ((64, 1), (128, 2), (128, 1), (256, 2), (256, 1), (512, 2), (512, 1), (512, 1),
                (512, 1), (512, 1), (512, 1), (1024, 2), (1024, 1))
#: NetAdapt-pruned FastDepth (fast-depth's ``mobilenet-nnconv5dw-skipadd-pruned``), read off the
#: TX2 kernel shapes in ``tx2-tvm-kernels/kernels.csv``: first conv, 13 encoder blocks, 5 decoder
#: stages (the last pointwise 16->1 convolution is the head).
PRUNED_FIRST = 16
PRUNED_ENCODER = (56, 88, 120, 144, 256, 408, 376, 272, 288, 296, 328, 480, 512)
PRUNED_DECODER = (200, 256, 120, 56, 16)


class FastDepth(nn.Module):
    """MobileNet v1 encoder, NNConv5 depthwise-separable decoder (5x5 dw, 1x1 pw, nearest x2),
    additive skips from blocks 1, 3 and 5 (fast-depth's ``MobileNetSkipAdd``)."""

    def __init__(self, first: int = 32, encoder: tuple[int, ...] = tuple(c for c, _ in MOBILENET_V1),
                 decoder: tuple[int, ...] = (512, 256, 128, 64, 32)) -> None:
        super().__init__()
        self.conv0 = conv_bn_relu(3, first, 3, 2)
        blocks, cin = [], first
        for cout, (_, stride) in zip(encoder, MOBILENET_V1):
            blocks.append(nn.Sequential(conv_bn_relu(cin, cin, 3, stride, groups=cin), conv_bn_relu(cin, cout, 1)))
            cin = cout
        self.encoder = nn.ModuleList(blocks)
        stages = []
        for cout in decoder:
            stages.append(nn.Sequential(conv_bn_relu(cin, cin, 5, groups=cin), conv_bn_relu(cin, cout, 1)))
            cin = cout
        self.decoder = nn.ModuleList(stages)
        self.upsample = nn.ModuleList(Resize(2) for _ in decoder)
        self.skip = nn.ModuleDict({str(i): SkipAdd() for i in (2, 3, 4)})
        self.head = conv_bn_relu(cin, 1, 1)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = self.conv0(image)
        skips = {}
        for i, block in enumerate(self.encoder, start=1):
            x = block(x)
            skips[i] = x
        for i, (stage, up) in enumerate(zip(self.decoder, self.upsample), start=1):
            x = up(stage(x))
            if str(i) in self.skip:   # decoder stage 4 meets block 1, 3 meets 3, 2 meets 5
                x = self.skip[str(i)](x, skips[{2: 5, 3: 3, 4: 1}[i]])
        return self.head(x)


# -- ResNet ----------------------------------------------------------------------------------------
class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, width: int, stride: int) -> None:
        super().__init__()
        cout = width * self.expansion
        self.body = nn.Sequential(conv_bn_relu(cin, width, 3, stride),
                                  nn.Conv2d(width, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout))
        self.shortcut = _projection(cin, cout, stride)
        self.add = SkipAdd()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.add(self.body(x), self.shortcut(x)))


class Bottleneck(BasicBlock):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int) -> None:
        nn.Module.__init__(self)
        cout = width * self.expansion
        self.body = nn.Sequential(conv_bn_relu(cin, width, 1), conv_bn_relu(width, width, 3, stride),
                                  nn.Conv2d(width, cout, 1, bias=False), nn.BatchNorm2d(cout))
        self.shortcut = _projection(cin, cout, stride)
        self.add = SkipAdd()


def _projection(cin: int, cout: int, stride: int) -> nn.Module:
    if cin == cout and stride == 1:
        return nn.Identity()
    return nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))


RESNETS = {18: (BasicBlock, (2, 2, 2, 2)), 50: (Bottleneck, (3, 4, 6, 3))}


class ResNetEncoder(nn.Module):
    """torchvision's ResNet without its classifier; returns the features after conv1 and after
    each of the four layers (strides 2, 4, 8, 16, 32)."""

    def __init__(self, depth: int, in_channels: int = 3) -> None:
        super().__init__()
        block, counts = RESNETS[depth]
        self.conv1 = conv_bn_relu(in_channels, 64, 7, 2)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        layers, cin = [], 64
        for i, n in enumerate(counts):
            width = 64 * 2 ** i
            blocks = []
            for j in range(n):
                blocks.append(block(cin, width, 2 if (j == 0 and i > 0) else 1))
                cin = width * block.expansion
            layers.append(nn.Sequential(*blocks))
        self.layers = nn.ModuleList(layers)
        self.out_channels = cin
        self.channels = (64, *(64 * 2 ** i * block.expansion for i in range(4)))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.conv1(x)
        feats = [x]
        x = self.maxpool(x)
        for layer in self.layers:
            x = layer(x)
            feats.append(x)
        return feats


# -- sparse-to-dense (Ma & Karaman) ----------------------------------------------------------------
class UpProj(nn.Module):
    """Laina et al.'s up-projection: un-pool x2, then 5x5 conv + 3x3 conv, plus a 5x5 conv shortcut."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.unpool = Resize(2)
        self.upper = nn.Sequential(conv_bn_relu(cin, cout, 5), nn.Conv2d(cout, cout, 3, 1, 1, bias=False),
                                   nn.BatchNorm2d(cout))
        self.lower = nn.Sequential(nn.Conv2d(cin, cout, 5, 1, 2, bias=False), nn.BatchNorm2d(cout))
        self.add = SkipAdd()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.unpool(x)
        return torch.relu(self.add(self.upper(x), self.lower(x)))


def _deconv2(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.ConvTranspose2d(cin, cout, 2, 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class SparseToDense(nn.Module):
    """RGB + sparse depth (4 channels) -> ResNet -> 1x1 conv halving the channels -> four decoder
    layers halving them again -> 3x3 conv to depth -> bilinear resize to the input size."""

    def __init__(self, depth: int, decoder: str = "deconv2") -> None:
        super().__init__()
        self.encoder = ResNetEncoder(depth, in_channels=4)
        c = self.encoder.out_channels // 2
        self.conv2 = nn.Sequential(nn.Conv2d(c * 2, c, 1, bias=False), nn.BatchNorm2d(c))
        layer = _deconv2 if decoder == "deconv2" else UpProj
        self.decoder = nn.Sequential(*(layer(c // 2 ** i, c // 2 ** (i + 1)) for i in range(4)))
        self.conv3 = nn.Conv2d(c // 16, 1, 3, 1, 1, bias=False)
        self.resize = nn.Upsample(mode="bilinear", align_corners=True)

    def forward(self, rgbd: torch.Tensor) -> torch.Tensor:
        x = self.conv3(self.decoder(self.conv2(self.encoder(rgbd)[-1])))
        self.resize.size = tuple(rgbd.shape[2:])
        return self.resize(x)


# -- MonoDepth2 ------------------------------------------------------------------------------------
def _conv3x3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, 1, 1, padding_mode="reflect")


class MonoDepth2(nn.Module):
    """MonoDepth2's depth network: ResNet-18 encoder, its DepthDecoder (reflection-padded 3x3 convs
    with ELU, nearest x2, concatenated skips) and sigmoid disparity heads at scales 0-3."""

    DECODER = (16, 32, 64, 128, 256)

    def __init__(self) -> None:
        super().__init__()
        self.encoder = ResNetEncoder(18)
        enc, dec = self.encoder.channels, self.DECODER
        self.upconv0 = nn.ModuleList(_conv3x3(enc[-1] if i == 4 else dec[i + 1], dec[i]) for i in range(5))
        self.upconv1 = nn.ModuleList(_conv3x3(dec[i] + (enc[i - 1] if i > 0 else 0), dec[i]) for i in range(5))
        self.upsample = nn.ModuleList(Resize(2) for _ in range(5))
        self.concat = nn.ModuleList(Concat() for _ in range(4))
        self.disp = nn.ModuleList(_conv3x3(dec[s], 1) for s in range(4))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feats = self.encoder(image)
        x, disps = feats[-1], []
        for i in range(4, -1, -1):
            x = self.upsample[i](torch.nn.functional.elu(self.upconv0[i](x)))
            if i > 0:
                x = self.concat[i - 1](x, feats[i - 1])
            x = torch.nn.functional.elu(self.upconv1[i](x))
            if i < 4:
                disps.append(torch.sigmoid(self.disp[i](x)))
        return tuple(disps)   # scales 3, 2, 1, 0: the full-resolution disparity comes last


# -- registry --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PaperFigure:
    """What is published for a reference network: the paper's Tables 1 and 3 (TX2 GPU latency with
    TVM, params, GFLOPs), or for the pruned FastDepth, fast-depth's own figures (5.6 ms on the TX2 GPU)."""

    input_size: tuple[int, int]
    latency_ms: float | None
    params_m: float
    gflops: float | None


@dataclass(frozen=True)
class Reference:
    name: str
    description: str
    build: Callable[[], nn.Module]
    in_channels: int
    paper: PaperFigure | None = None
    stride: int = 32
    min_side: int = 32      # smallest input side it runs at (reflection padding needs 2 pixels at stride 32)

    def input_shape(self, input_size: tuple[int, int]) -> tuple[int, int, int, int]:
        return (1, self.in_channels, *input_size)


REFERENCES: dict[str, Reference] = {r.name: r for r in (
    Reference("fastdepth", "FastDepth (MobileNet v1 + NNConv5 depthwise decoder, skip-add), Wofk et al.",
              FastDepth, 3, PaperFigure((224, 224), 17.1, 4.016, 0.867)),
    Reference("fastdepth-pruned", "FastDepth after NetAdapt pruning (fast-depth's published model)",
              lambda: FastDepth(PRUNED_FIRST, PRUNED_ENCODER, PRUNED_DECODER), 3,
              PaperFigure((224, 224), 5.6, 1.34, 0.37)),
    Reference("s2d-resnet50", "sparse-to-dense, Ma & Karaman: RGB-D, ResNet-50, deconv2 decoder (paper Table 1)",
              lambda: SparseToDense(50), 4, PaperFigure((228, 304), 554.7, 28.39, 8.910)),
    Reference("s2d-resnet18", "sparse-to-dense, Ma & Karaman: RGB-D, ResNet-18, deconv2 decoder (paper Table 3)",
              lambda: SparseToDense(18), 4, PaperFigure((228, 912), 374.7, 11.49, 8.593)),
    Reference("s2d-resnet50-upproj", "sparse-to-dense, Ma & Karaman: RGB-D, ResNet-50, UpProj decoder",
              lambda: SparseToDense(50, "upproj"), 4),
    Reference("s2d-resnet18-upproj", "sparse-to-dense, Ma & Karaman: RGB-D, ResNet-18, UpProj decoder",
              lambda: SparseToDense(18, "upproj"), 4),
    Reference("monodepth2-resnet18", "MonoDepth2 depth network (ResNet-18 + depth decoder, 4 disparity scales)",
              MonoDepth2, 3, PaperFigure((192, 640), 77.26, 15.24, 8.051), min_side=64),
)}


def get_reference(name: str) -> Reference:
    try:
        return REFERENCES[name]
    except KeyError:
        raise UserError(f"unknown reference network '{name}' (and no such candidate or space file): "
                        f"known are {', '.join(REFERENCES)}") from None


# -- as a study's baseline -------------------------------------------------------------------------
@dataclass(frozen=True)
class ReferenceModel:
    """A reference network in a study: what its trials and checkpoints record in place of a candidate."""

    name: str
    num_paths: int = 2    # path 0 (the scan) and the network's one output
    precision: str = "fp32"   # trained and costed as published

    @property
    def key(self) -> str:
        return f"ref-{self.name}"

    def to_dict(self) -> dict:
        return {"reference": self.name}

    @property
    def stride(self) -> int:
        return get_reference(self.name).stride

    @property
    def min_side(self) -> int:
        return get_reference(self.name).min_side

    def describe(self) -> str:
        return get_reference(self.name).description


class ReferenceDepthNet(nn.Module):
    """A reference network trained and evaluated as a candidate is: ``forward(image, scan, scan_row)``
    returns [path 0 (the scan, nearest column, as every candidate has), the network's depth]. The
    sparse-to-dense networks take the scan as their sparse depth channel (on its row, zeros
    elsewhere), as Ma & Karaman feed sampled LiDAR depth; MonoDepth2's full-resolution disparity
    becomes depth as MonoDepth2 does (1 / disparity scaled to 0.1-100 m)."""

    MIN_DEPTH, MAX_DEPTH = 0.1, 100.0

    def __init__(self, name: str) -> None:
        super().__init__()
        ref = get_reference(name)
        self.candidate = ReferenceModel(name)
        self.in_channels = ref.in_channels
        self.stride = ref.stride
        self.network = ref.build()

    def forward(self, image: torch.Tensor, scan: torch.Tensor, scan_row: "int | torch.Tensor | None" = None
                ) -> list[torch.Tensor]:
        n, _, h, w = image.shape
        if h % self.stride or w % self.stride or min(h, w) < self.candidate.min_side:
            raise UserError(f"{self.candidate.name} needs sides divisible by {self.stride} and at least "
                            f"{self.candidate.min_side}, got {h}x{w}")
        x = image
        if self.in_channels == 4:
            sparse = image.new_zeros(n, 1, h, w)
            if isinstance(scan_row, torch.Tensor) and scan_row.dim() == 2:   # each column on its own row
                rows = scan_row.to(image.device, torch.int64).clamp(0, h - 1)
                sparse.scatter_(2, rows[:, None, None, :], scan.to(image.dtype)[:, None, None, :])
            else:
                sparse[:, 0, h // 2 if scan_row is None else int(scan_row), :] = scan.to(image.dtype)
            x = torch.cat([image, sparse], dim=1)
        out = self.network(x)
        if isinstance(out, tuple):
            lo, hi = 1.0 / self.MAX_DEPTH, 1.0 / self.MIN_DEPTH
            out = 1.0 / (lo + (hi - lo) * out[-1])
        return [interpolate_scan(scan, h).to(out.dtype), out]
