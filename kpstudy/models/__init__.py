"""Keypoint networks: backbones that output unnormalised heatmaps, the target heads
(softmax → DSNT or argmax) and the proxy head that turns the heatmaps into a verifiable
per-keypoint classification (docs/design.md §4.5).

Every backbone has class attributes ``input_size`` (square input side, pixels) and
``heatmap_size`` (square heatmap side, pixels) and uses only the operators the verifier
bounds (:mod:`kpstudy.verify.graph`).
"""

from torch import nn

from kpstudy.models.cnn import HeatmapCNN, HeatmapCNNAffineDecoder
from kpstudy.models.heads import (
    TargetModel,
    argmax_keypoints,
    dsnt_keypoints,
    softmax_heatmaps,
)
from kpstudy.models.proxy import KeypointProxy, build_proxy
from kpstudy.models.resnet import HeatmapResNet18

BACKBONES = {
    "cnn": HeatmapCNN,
    "cnn_affine": HeatmapCNNAffineDecoder,
    "resnet18": HeatmapResNet18,
}


def build_backbone(name: str, num_keypoints: int = 23) -> nn.Module:
    """A freshly initialised heatmap backbone.

    Parameters
    ----------
    name : {'cnn', 'cnn_affine', 'resnet18'}
        ``'cnn'``: 64×64 input and heatmaps, ~6.6e5 parameters; ``'cnn_affine'``: the same
        with an affine decoder (no ReLU after the transposed convolutions, the
        verification-friendly model); ``'resnet18'``: 256×256 input and heatmaps, ~1.25e7
        parameters.
    num_keypoints : int
        Heatmap channels.

    Examples
    --------
    >>> build_backbone("cnn").input_size
    64
    """
    if name not in BACKBONES:
        raise ValueError(f"name: expected one of {sorted(BACKBONES)}, got {name!r}")
    if isinstance(num_keypoints, bool) or not isinstance(num_keypoints, int) or num_keypoints < 1:
        raise ValueError(f"num_keypoints: expected a positive integer, got {num_keypoints!r}")
    return BACKBONES[name](num_keypoints)


__all__ = [
    "BACKBONES",
    "HeatmapCNN",
    "HeatmapCNNAffineDecoder",
    "HeatmapResNet18",
    "KeypointProxy",
    "TargetModel",
    "argmax_keypoints",
    "build_backbone",
    "build_proxy",
    "dsnt_keypoints",
    "softmax_heatmaps",
]
