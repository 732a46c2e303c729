"""The proxy model: backbone → per-keypoint cell pooling → flatten → concatenation.

Softmax + DSNT/argmax heads are replaced by one :class:`~kpstudy.pooling.CellAvgPool2d`
per heatmap channel, built around the keypoint's nominal heatmap pixel with its allocated
tolerance, so that "the keypoint's cell wins" is a linear classification spec
(paper §5.3, DESIGN.md §4.4–4.6).
"""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.pooling import build_cell_pool
from kpstudy.verify.spec import ArgmaxSpec


class KeypointProxy(nn.Module):
    """Pool each heatmap channel on its own cells; output ``(B, Σ_k cells_k)``.

    Parameters
    ----------
    backbone : nn.Module
        ``(B, *S) → (B, K, H, W)`` unnormalised heatmaps.
    pools : sequence of CellAvgPool2d
        One per channel, in channel order.
    """

    def __init__(self, backbone: nn.Module, pools) -> None:
        super().__init__()
        self.backbone = backbone
        self.pools = nn.ModuleList(pools)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.backbone(x)
        cells = [pool(h[:, k : k + 1]).flatten(1) for k, pool in enumerate(self.pools)]
        return torch.cat(cells, 1)


def build_proxy(backbone: nn.Module, centers, dv, heatmap_size, verified=None):
    """The proxy of ``backbone`` and its argmax spec.

    Parameters
    ----------
    backbone : nn.Module
        Outputs ``(B, K, H, W)``.
    centers : array_like of int, shape (K, 2)
        Nominal keypoints ``(u, v)`` in heatmap pixels.
    dv : array_like of int, shape (K, 2)
        Tolerances ``(δu, δv)`` in heatmap pixels.
    heatmap_size : (int, int)
        ``(H, W)``.
    verified : sequence of bool, optional
        Keypoints to verify (default all); the others get no spec rows.

    Returns
    -------
    proxy : KeypointProxy
    spec : ArgmaxSpec
        Group ``k`` is keypoint ``k``'s cells; its target is the cell of ``centers[k]``.
    """
    centers, dv = [tuple(map(int, c)) for c in centers], [tuple(map(int, d)) for d in dv]
    if len(centers) != len(dv):
        raise ValueError(f"dv: expected {len(centers)} rows (one per center), got {len(dv)}")
    made = [build_cell_pool(c, d, heatmap_size) for c, d in zip(centers, dv)]
    verified = [True] * len(made) if verified is None else list(verified)
    if len(verified) != len(made):
        raise ValueError(f"verified: expected {len(made)} entries, got {len(verified)}")
    sizes = [p.n_v * p.n_h for p, _ in made]
    targets = [t if keep else None for (_, t), keep in zip(made, verified)]
    return KeypointProxy(backbone, [p for p, _ in made]), ArgmaxSpec(sizes, targets)
