"""The paper's CNN backbone: 5 convolutions and 5 transposed convolutions (paper §8.1).

Input ``(B, 3, 64, 64)`` (a normalised, resized image) → unnormalised heatmaps
``(B, K, 64, 64)``. Encoder: 3×3 convolutions, two of stride 2 (64 → 16 px); decoder:
transposed convolutions back to 64 px; batch norm and ReLU after every layer but the
last. About 6.6e5 parameters for K = 23, as in the paper (6.57e5).

:class:`HeatmapCNNAffineDecoder` is the verification-friendly variant: the same layers
with no ReLU after the transposed convolutions, so the decoder (its batch norms folded)
is one affine map, a learned linear upsampler. Every bound method maps a zonotope through
it exactly: the heatmaps' bounds are as tight as the encoder's.
"""

from __future__ import annotations

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

    def __init__(self, keypoints: int = 23) -> None:
        layers: list[nn.Module] = []
        for c_in, c_out, stride in _ENCODER:
            layers += [nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out)]
            layers.append(nn.ReLU())
        for c_in, c_out, stride in _DECODER:
            kernel = 4 if stride == 2 else 3
            layers.append(nn.ConvTranspose2d(c_in, c_out, kernel, stride, 1, bias=False))
            layers.append(nn.BatchNorm2d(c_out))
            if self.decoder_relu:
                layers.append(nn.ReLU())
        layers.append(nn.ConvTranspose2d(_DECODER[-1][1], keypoints, 3, 1, 1))
        super().__init__(*layers)
        self.keypoints = keypoints


class HeatmapCNNAffineDecoder(HeatmapCNN):
    """:class:`HeatmapCNN` without the decoder's ReLUs: ``(B, 3, 64, 64) → (B, K, 64, 64)``,
    the same parameters, the heatmaps an affine function of the encoder's last ReLU."""

    decoder_relu = False
