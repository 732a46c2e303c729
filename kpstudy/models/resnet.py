"""ResNet-18 heatmap backbone (paper §8.1): ResNet-18 encoder, transposed-convolution decoder.

Input ``(B, 3, 256, 256)`` → unnormalised heatmaps ``(B, K, 256, 256)``. The encoder is
He et al.'s ResNet-18 without its classifier (a 7×7 stem of stride 2, a 3×3 max pool of
stride 2, four stages of two basic blocks; 256 → 8 px, 512 channels). The decoder is five
4×4 transposed convolutions of stride 2 (8 → 256 px) with batch norm and ReLU, then a
1×1 convolution to the K heatmaps. About 1.25e7 parameters for K = 23 (paper: 1.2e7).
Written here (no CPU build of torchvision) from the operators the verifier bounds:
Conv2d, ConvTranspose2d, BatchNorm2d, ReLU, MaxPool2d and the residual ``+``.
"""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models.base import HeatmapBackbone

_STAGES = [(64, 64, 1), (64, 128, 2), (128, 256, 2), (256, 512, 2)]
_DECODER = [512, 128, 64, 64, 32, 32]


def _conv_bn(c_in: int, c_out: int, kernel: int, stride: int) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, kernel, stride, kernel // 2, bias=False), nn.BatchNorm2d(c_out)]


class BasicBlock(nn.Module):
    """``relu(bn(conv(relu(bn(conv(x))))) + shortcut(x))``; the shortcut is a strided 1×1
    convolution with batch norm when the shape changes, else the identity."""

    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            *_conv_bn(c_in, c_out, 3, stride), nn.ReLU(), *_conv_bn(c_out, c_out, 3, 1)
        )
        changes = stride != 1 or c_in != c_out
        self.shortcut = nn.Sequential(*_conv_bn(c_in, c_out, 1, stride)) if changes else None
        self.relu = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skip = x if self.shortcut is None else self.shortcut(x)
        return self.relu(self.body(x) + skip)


class HeatmapResNet18(HeatmapBackbone):
    """Heatmap backbone ``(B, 3, 256, 256) → (B, K, 256, 256)`` with ``K = keypoints``
    (see the module docstring for its layers)."""

    input_size = 256
    heatmap_size = 256

    def __init__(self, keypoints: int = 23) -> None:
        layers: list[nn.Module] = [*_conv_bn(3, 64, 7, 2), nn.ReLU(), nn.MaxPool2d(3, 2, 1)]
        for c_in, c_out, stride in _STAGES:
            layers += [BasicBlock(c_in, c_out, stride), BasicBlock(c_out, c_out, 1)]
        for c_in, c_out in zip(_DECODER, _DECODER[1:]):
            layers.append(nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=False))
            layers += [nn.BatchNorm2d(c_out), nn.ReLU()]
        layers.append(nn.Conv2d(_DECODER[-1], keypoints, 1))
        super().__init__(*layers)
        self.keypoints = keypoints
