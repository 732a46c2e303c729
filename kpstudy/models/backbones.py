"""The backbones by name: :data:`BACKBONES` and :func:`build_backbone`."""

from torch import nn

from kpstudy import _checks
from kpstudy.models.cnn import (
    HeatmapCNN,
    HeatmapCNNAffineDecoder,
    HeatmapCNNPatchDecoder,
    HeatmapCNNPatchSmoothDecoder,
)
from kpstudy.models.resnet import HeatmapResNet18

#: The backbone classes by the name :func:`build_backbone` takes.
BACKBONES = {
    "cnn": HeatmapCNN,
    "cnn_affine": HeatmapCNNAffineDecoder,
    "cnn_patch": HeatmapCNNPatchDecoder,
    "cnn_patch_smooth": HeatmapCNNPatchSmoothDecoder,
    "resnet18": HeatmapResNet18,
}


def build_backbone(name: str, num_keypoints: int = 23) -> nn.Module:
    """A freshly initialised heatmap backbone.

    Parameters
    ----------
    name : {'cnn', 'cnn_affine', 'cnn_patch', 'cnn_patch_smooth', 'resnet18'}
        ``'cnn'``: 64×64 input and heatmaps, ~6.6e5 parameters; ``'cnn_affine'``: the same
        with an affine decoder (no ReLU after the transposed convolutions);
        ``'cnn_patch'``: the same encoder with an affine decoder whose transposed
        convolutions' kernels equal their strides, ~3.6e5 parameters;
        ``'cnn_patch_smooth'``: that decoder then a per-keypoint 3×3 filter (the
        verification-friendly model); ``'resnet18'``: 256×256 input and heatmaps,
        ~1.25e7 parameters.
    num_keypoints : int
        Heatmap channels.

    Examples
    --------
    >>> build_backbone("cnn").input_size
    64
    """
    _checks.choice(name, "name", sorted(BACKBONES))
    _checks.integer(num_keypoints, "num_keypoints", minimum=1)
    return BACKBONES[name](num_keypoints)
