"""The paper's CNN backbone: 5 convolutions and 5 transposed convolutions (paper §8.1).

Input ``(B, 3, 64, 64)`` (a normalised, resized image) → unnormalised heatmaps
``(B, K, 64, 64)``. Encoder: 3×3 convolutions, two of stride 2 (64 → 16 px); decoder:
transposed convolutions back to 64 px; batch norm and ReLU after every layer but the
last. About 6.6e5 parameters for K = 23, as in the paper (6.57e5).

:class:`HeatmapCNNAffineDecoder`: the same layers with no ReLU after the transposed
convolutions, so the decoder (its batch norms folded) is one affine map, a learned linear
upsampler. Every bound method maps a zonotope through it exactly: the heatmaps' bounds are
as tight as the encoder's. :class:`HeatmapCNNPatchDecoder` also makes every transposed
convolution's kernel its stride, so each encoder position drives its own 4×4 patch of the
heatmaps and the zonotope's error symbols cost the decoder a sixth or less of the
multiply-adds. :class:`HeatmapCNNPatchSmoothDecoder`, the verification-friendly model
kpstudy ships, adds a per-keypoint 3×3 filter after it, which places keypoints about as
precisely as the paper's decoder (docs/design.md §4.5b).
"""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models.base import HeatmapBackbone

_ENCODER = [(3, 32, 1), (32, 64, 2), (64, 64, 1), (64, 128, 2), (128, 128, 1)]
_DECODER = [(128, 128, 2), (128, 64, 1), (64, 32, 2), (32, 32, 1)]


class HeatmapCNN(HeatmapBackbone):
    """Heatmap backbone ``(B, 3, 64, 64) → (B, K, 64, 64)``.

    Parameters
    ----------
    keypoints : int
        Heatmap channels ``K`` (23 for the airliner).

    Examples
    --------
    >>> net = HeatmapCNN(23).eval()
    >>> net(torch.zeros(1, 3, 64, 64)).shape  # doctest: +SKIP
    torch.Size([1, 23, 64, 64])
    """

    input_size = 64
    heatmap_size = 64

    decoder_relu = True
    #: Transposed convolutions' kernel sizes for stride 2 and stride 1.
    decoder_kernels = (4, 3)

    def __init__(self, keypoints: int = 23) -> None:
        layers: list[nn.Module] = []
        for c_in, c_out, stride in _ENCODER:
            layers += [nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out)]
            layers.append(nn.ReLU())
        for c_in, c_out, stride in _DECODER:
            layers += [self._upsample(c_in, c_out, stride, bias=False), nn.BatchNorm2d(c_out)]
            if self.decoder_relu:
                layers.append(nn.ReLU())
        layers.append(self._upsample(_DECODER[-1][1], keypoints, 1, bias=True))
        super().__init__(*layers)
        self.keypoints = keypoints

    @classmethod
    def _upsample(cls, c_in: int, c_out: int, stride: int, bias: bool) -> nn.ConvTranspose2d:
        """A decoder layer: ``(B, c_in, h, w) → (B, c_out, stride·h, stride·w)``."""
        kernel = cls.decoder_kernels[0] if stride == 2 else cls.decoder_kernels[1]
        return nn.ConvTranspose2d(c_in, c_out, kernel, stride, (kernel - stride) // 2, bias=bias)


class HeatmapCNNAffineDecoder(HeatmapCNN):
    """:class:`HeatmapCNN` without the decoder's ReLUs: ``(B, 3, 64, 64) → (B, K, 64, 64)``,
    the same parameters, the heatmaps an affine function of the encoder's last ReLU."""

    decoder_relu = False


class HeatmapCNNPatchDecoder(HeatmapCNNAffineDecoder):
    """:class:`HeatmapCNNAffineDecoder` with transposed convolutions whose kernel equals
    their stride (2×2 at stride 2, 1×1 at stride 1): ``(B, 3, 64, 64) → (B, K, 64, 64)``.

    The decoder maps each encoder position's 128 features to its own 4×4 patch of the
    heatmaps (one affine map per position, shared), so an error symbol's window does not
    grow through it and a zonotope costs a sixth or less of
    :class:`HeatmapCNNAffineDecoder`'s multiply-adds there; ~3.6e5 parameters for K = 23."""

    decoder_kernels = (2, 1)


class HeatmapCNNPatchSmoothDecoder(HeatmapCNNPatchDecoder):
    """:class:`HeatmapCNNPatchDecoder` followed by a per-keypoint 3×3 linear filter
    (a depthwise convolution without bias, initialised to the identity):
    ``(B, 3, 64, 64) → (B, K, 64, 64)``. Each heatmap pixel then reads the patches of up
    to four encoder positions, at 9 multiply-adds per pixel and keypoint; the decoder
    stays affine."""

    smoothing = 3

    def __init__(self, keypoints: int = 23) -> None:
        super().__init__(keypoints)
        k = self.smoothing
        smooth = nn.Conv2d(keypoints, keypoints, k, 1, k // 2, groups=keypoints, bias=False)
        with torch.no_grad():
            smooth.weight.zero_()
            smooth.weight[:, 0, k // 2, k // 2] = 1.0
        self.append(smooth)
