"""Convolutional trunks for visuomotor policies, written out here (no torchvision, no weights).

Every backbone maps ``x: (B, 3, H, W)`` (already normalized) to its last convolutional feature map
``A: (B, C, h, w)`` and exposes ``out_channels = C``. Only the trunk is built: no classifier, no
global pooling (the policy head decides how to read ``A``).

Parameter counts equal the standard architectures' trunks:

================  ===========  ======================================================
name              parameters   trunk
================  ===========  ======================================================
``resnet18``      11,176,512   ResNet-18 without ``fc``
``resnet34``      21,284,672   ResNet-34 without ``fc``
``vgg16``         14,723,136   VGG16-BN ``features``
``inception_v3``  21,785,568   Inception-v3 up to ``Mixed_7c``, without ``AuxLogits``/``fc``
``small_cnn``     (small)      four conv-BN-ReLU layers, for fast tests and the quick preset
================  ===========  ======================================================

Small-image stem (``small_stem=True``, the default for policies; 64-128 px wrist images): the
standard trunks shrink 224 px by 32, which leaves a 2x2 map at 64 px (too coarse for Grad-CAM and
for localising the goal) and breaks Inception-v3 outright (its unpadded stem needs >= 75 px). The
small stem removes *parameter-free* downsampling only, so parameter counts are unchanged:

* ResNet: no max-pool after ``conv1`` (total stride 16: 64 px -> 4x4, 128 px -> 8x8).
* VGG16-BN: no final max-pool (total stride 16).
* Inception-v3: padding 1 on the stem's unpadded 3x3 convs (``Conv2d_1a``, ``Conv2d_2a``,
  ``Conv2d_4a``) and no second stem max-pool (64 px -> 3x3 after ``Mixed_7c``, 128 px -> 7x7).

All activations are out-of-place, so second derivatives (``create_graph=True``, needed for a
differentiable Grad-CAM) work through every trunk.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["BACKBONES", "build_backbone", "ResNet", "VGG16BN", "InceptionV3", "SmallCNN"]


def _conv_bn(
    cin: int, cout: int, k: int, stride: int = 1, padding: int | tuple = 0, eps: float = 1e-5
) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, padding, bias=False), nn.BatchNorm2d(cout, eps=eps), nn.ReLU())


# ---------------------------------------------------------------------------------------- ResNet
class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 convs) with a 1x1 projection shortcut when the shape changes."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return F.relu(out + identity)


class ResNet(nn.Module):
    """ResNet trunk with basic blocks; ``layers`` = blocks per stage ((2,2,2,2) = ResNet-18)."""

    def __init__(self, layers: tuple[int, int, int, int], small_stem: bool = True):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.maxpool = nn.Identity() if small_stem else nn.MaxPool2d(3, 2, 1)
        stages, cin = [], 64
        for i, (n, cout) in enumerate(zip(layers, (64, 128, 256, 512))):
            blocks = [BasicBlock(cin, cout, 1 if i == 0 else 2)] + [BasicBlock(cout, cout, 1) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = cout
        self.layer1, self.layer2, self.layer3, self.layer4 = stages
        self.out_channels = 512

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


def resnet18(small_stem: bool = True) -> ResNet:
    return ResNet((2, 2, 2, 2), small_stem)


def resnet34(small_stem: bool = True) -> ResNet:
    return ResNet((3, 4, 6, 3), small_stem)


# ---------------------------------------------------------------------------------------- VGG
VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")


class VGG16BN(nn.Module):
    """VGG16 with batch norm: the 13 conv layers of ``features``."""

    def __init__(self, small_stem: bool = True):
        super().__init__()
        cfg = VGG16_CFG[:-1] if small_stem else VGG16_CFG
        layers, cin = [], 3
        for v in cfg:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, v, 3, padding=1), nn.BatchNorm2d(v), nn.ReLU()]
                cin = v
        self.features = nn.Sequential(*layers)
        self.out_channels = 512

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)


# ---------------------------------------------------------------------------------------- Inception-v3
def _bc(cin: int, cout: int, k, stride: int = 1, padding=0) -> nn.Sequential:
    # Inception-v3's BasicConv2d: conv without bias, BN with eps 1e-3, ReLU.
    return _conv_bn(cin, cout, k, stride, padding, eps=1e-3)


class InceptionA(nn.Module):
    def __init__(self, cin: int, pool_features: int):
        super().__init__()
        self.branch1x1 = _bc(cin, 64, 1)
        self.branch5x5 = nn.Sequential(_bc(cin, 48, 1), _bc(48, 64, 5, padding=2))
        self.branch3x3dbl = nn.Sequential(_bc(cin, 64, 1), _bc(64, 96, 3, padding=1), _bc(96, 96, 3, padding=1))
        self.branch_pool = _bc(cin, pool_features, 1)

    def forward(self, x):
        pool = self.branch_pool(F.avg_pool2d(x, 3, 1, 1))
        return torch.cat([self.branch1x1(x), self.branch5x5(x), self.branch3x3dbl(x), pool], 1)


class InceptionB(nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3 = _bc(cin, 384, 3, stride=2)
        self.branch3x3dbl = nn.Sequential(_bc(cin, 64, 1), _bc(64, 96, 3, padding=1), _bc(96, 96, 3, stride=2))

    def forward(self, x):
        return torch.cat([self.branch3x3(x), self.branch3x3dbl(x), F.max_pool2d(x, 3, 2)], 1)


class InceptionC(nn.Module):
    def __init__(self, cin: int, c7: int):
        super().__init__()
        self.branch1x1 = _bc(cin, 192, 1)
        self.branch7x7 = nn.Sequential(
            _bc(cin, c7, 1), _bc(c7, c7, (1, 7), padding=(0, 3)), _bc(c7, 192, (7, 1), padding=(3, 0))
        )
        self.branch7x7dbl = nn.Sequential(
            _bc(cin, c7, 1),
            _bc(c7, c7, (7, 1), padding=(3, 0)),
            _bc(c7, c7, (1, 7), padding=(0, 3)),
            _bc(c7, c7, (7, 1), padding=(3, 0)),
            _bc(c7, 192, (1, 7), padding=(0, 3)),
        )
        self.branch_pool = _bc(cin, 192, 1)

    def forward(self, x):
        pool = self.branch_pool(F.avg_pool2d(x, 3, 1, 1))
        return torch.cat([self.branch1x1(x), self.branch7x7(x), self.branch7x7dbl(x), pool], 1)


class InceptionD(nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3 = nn.Sequential(_bc(cin, 192, 1), _bc(192, 320, 3, stride=2))
        self.branch7x7x3 = nn.Sequential(
            _bc(cin, 192, 1),
            _bc(192, 192, (1, 7), padding=(0, 3)),
            _bc(192, 192, (7, 1), padding=(3, 0)),
            _bc(192, 192, 3, stride=2),
        )

    def forward(self, x):
        return torch.cat([self.branch3x3(x), self.branch7x7x3(x), F.max_pool2d(x, 3, 2)], 1)


class InceptionE(nn.Module):
    def __init__(self, cin: int):
        super().__init__()
        self.branch1x1 = _bc(cin, 320, 1)
        self.branch3x3_1 = _bc(cin, 384, 1)
        self.branch3x3_2a = _bc(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3_2b = _bc(384, 384, (3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = nn.Sequential(_bc(cin, 448, 1), _bc(448, 384, 3, padding=1))
        self.branch3x3dbl_3a = _bc(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = _bc(384, 384, (3, 1), padding=(1, 0))
        self.branch_pool = _bc(cin, 192, 1)

    def forward(self, x):
        b3 = self.branch3x3_1(x)
        b3 = torch.cat([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], 1)
        bd = self.branch3x3dbl_1(x)
        bd = torch.cat([self.branch3x3dbl_3a(bd), self.branch3x3dbl_3b(bd)], 1)
        pool = self.branch_pool(F.avg_pool2d(x, 3, 1, 1))
        return torch.cat([self.branch1x1(x), b3, bd, pool], 1)


class InceptionV3(nn.Module):
    """Inception-v3 trunk (``Conv2d_1a`` .. ``Mixed_7c``); see the module docstring for the stem."""

    def __init__(self, small_stem: bool = True):
        super().__init__()
        p = 1 if small_stem else 0
        self.stem = nn.Sequential(
            _bc(3, 32, 3, stride=2, padding=p),  # Conv2d_1a_3x3
            _bc(32, 32, 3, padding=p),  # Conv2d_2a_3x3
            _bc(32, 64, 3, padding=1),  # Conv2d_2b_3x3
            nn.MaxPool2d(3, 2),
            _bc(64, 80, 1),  # Conv2d_3b_1x1
            _bc(80, 192, 3, padding=p),  # Conv2d_4a_3x3
            nn.Identity() if small_stem else nn.MaxPool2d(3, 2),
        )
        self.mixed = nn.Sequential(
            InceptionA(192, 32),
            InceptionA(256, 64),
            InceptionA(288, 64),  # Mixed_5b/c/d
            InceptionB(288),  # Mixed_6a
            InceptionC(768, 128),
            InceptionC(768, 160),
            InceptionC(768, 160),
            InceptionC(768, 192),  # Mixed_6b-e
            InceptionD(768),  # Mixed_7a
            InceptionE(1280),
            InceptionE(2048),  # Mixed_7b/c
        )
        self.out_channels = 2048

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mixed(self.stem(x))


# ---------------------------------------------------------------------------------------- small CNN
class SmallCNN(nn.Module):
    """Four 3x3 conv-BN-ReLU layers, total stride 8 (64 px -> 8x8): for tests and quick training."""

    def __init__(self, small_stem: bool = True, width: int = 32):
        super().__init__()
        # small_stem is accepted for a uniform constructor; this trunk is small-image by design.
        w = width
        self.features = nn.Sequential(
            _conv_bn(3, w, 5, stride=2, padding=2),
            _conv_bn(w, 2 * w, 3, stride=2, padding=1),
            _conv_bn(2 * w, 2 * w, 3, stride=1, padding=1),
            _conv_bn(2 * w, 4 * w, 3, stride=2, padding=1),
        )
        self.out_channels = 4 * w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)


# The explicit name -> constructor table; policy cards store these names.
BACKBONES = {
    "resnet18": resnet18,
    "resnet34": resnet34,
    "vgg16": VGG16BN,
    "inception_v3": InceptionV3,
    "small_cnn": SmallCNN,
}


def build_backbone(name: str, small_stem: bool = True) -> nn.Module:
    """The trunk called ``name`` (a key of :data:`BACKBONES`), freshly initialised."""
    try:
        ctor = BACKBONES[name]
    except KeyError:
        raise ValueError(f"arch: unknown backbone {name!r}; choose one of {sorted(BACKBONES)}") from None
    return ctor(small_stem=small_stem)
