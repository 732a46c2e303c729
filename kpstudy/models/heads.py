"""Target heads: unnormalised heatmaps → keypoints (paper §3.1, docs/design.md §4.5).

Both normalise the heatmaps with a spatial softmax (kornia). DSNT takes the softmax's
mean (kornia's ``spatial_expectation2d``); argmax takes its mode, which is also the mode
of the unnormalised heatmap. On a heatmap whose row and column marginals are symmetric
about their mode the two agree (paper Proposition 1).
"""

from __future__ import annotations

import torch
from kornia.geometry.subpix import spatial_expectation2d, spatial_softmax2d
from torch import nn

from kpstudy import _checks


def _check(heatmaps) -> torch.Tensor:
    if not isinstance(heatmaps, torch.Tensor) or heatmaps.ndim != 4:
        shape = tuple(heatmaps.shape) if isinstance(heatmaps, torch.Tensor) else type(heatmaps)
        raise ValueError(f"heatmaps: expected a (B, K, H, W) tensor, got {shape}")
    return heatmaps


def softmax_heatmaps(heatmaps: torch.Tensor) -> torch.Tensor:
    """``(B, K, H, W)`` logits → per-channel probability maps of the same shape."""
    return spatial_softmax2d(_check(heatmaps))


def dsnt_keypoints(heatmaps: torch.Tensor) -> torch.Tensor:
    """DSNT keypoints ``(B, K, 2)`` as ``(u, v)`` heatmap pixels (differentiable).

    Examples
    --------
    >>> h = torch.full((1, 1, 5, 7), -1e4); h[0, 0, 1, 4] = 0.0
    >>> dsnt_keypoints(h)
    tensor([[[4., 1.]]])
    """
    return spatial_expectation2d(softmax_heatmaps(heatmaps), normalized_coordinates=False)


def argmax_keypoints(heatmaps: torch.Tensor) -> torch.Tensor:
    """Argmax keypoints ``(B, K, 2)`` as integer ``(u, v)`` heatmap pixels (first maximum
    in row-major order)."""
    B, K, H, W = _check(heatmaps).shape
    flat = heatmaps.reshape(B, K, H * W).argmax(-1)
    return torch.stack([flat % W, flat // W], -1)


class TargetModel(nn.Module):
    """Backbone + target head: images ``(B, 3, s, s)`` → keypoints ``(B, K, 2)`` in heatmap
    pixels.

    Parameters
    ----------
    backbone : nn.Module
        ``(B, 3, s, s) → (B, K, H, W)`` unnormalised heatmaps.
    head : {'dsnt', 'argmax'}
    """

    HEADS = {"dsnt": dsnt_keypoints, "argmax": argmax_keypoints}

    def __init__(self, backbone: nn.Module, head: str = "dsnt") -> None:
        super().__init__()
        _checks.choice(head, "head", sorted(self.HEADS))
        self.backbone, self.head = backbone, head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.HEADS[self.head](self.backbone(x))
