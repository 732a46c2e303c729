"""The proxy model: backbone → per-keypoint cell pooling → flatten → concatenation.

Softmax + DSNT/argmax heads are replaced by one :class:`~kpstudy.models.pooling.CellAvgPool2d`
per heatmap channel, built around the keypoint's nominal heatmap pixel with its allocated
tolerance, so that "the keypoint's cell wins" is a linear classification spec
(paper §5.2 and §6.3, docs/design.md §4.4–4.6).
"""

from __future__ import annotations

import operator

import numpy as np
import torch
from torch import nn

from kpstudy.models.pooling import CellAvgPool2d, cell_index
from kpstudy.verify.spec import ArgmaxSpec


class KeypointProxy(nn.Module):
    """Pool each heatmap channel on its own cells; output ``(B, Σ_k cells_k)``.

    Parameters
    ----------
    backbone : nn.Module
        ``(B, *S) → (B, K, H, W)`` unnormalised heatmaps.
    pools : sequence of CellAvgPool2d
        One per channel, in channel order.

    Attributes
    ----------
    index_map : numpy.ndarray of int, shape (n_outputs, 2)
        Output index → ``(keypoint, cell)``; a cell is the row-major flat index in the
        keypoint's ``(n_v, n_h)`` grid.
    target_cells : list of int or None
        Each keypoint's target cell (the cell of its nominal pixel), or ``None`` when the
        proxy was built without centres.
    spec : ArgmaxSpec or None
        "Each verified keypoint's target cell wins" (``None`` without centres).
    """

    def __init__(self, backbone: nn.Module, pools, target_cells=None, verified=None) -> None:
        super().__init__()
        self.backbone = backbone
        self.pools = nn.ModuleList(pools)
        sizes = [p.n_v * p.n_h for p in self.pools]
        self.index_map = np.array([(k, c) for k, n in enumerate(sizes) for c in range(n)])
        self.target_cells = None if target_cells is None else list(target_cells)
        self.spec = None
        if self.target_cells is not None:
            keep = [True] * len(sizes) if verified is None else list(verified)
            if len(keep) != len(sizes):
                raise ValueError(f"verified: expected {len(sizes)} entries, got {len(keep)}")
            targets = [t if k else None for t, k in zip(self.target_cells, keep)]
            self.spec = ArgmaxSpec(sizes, targets)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.backbone(x)
        cells = [pool(h[:, k : k + 1]).flatten(1) for k, pool in enumerate(self.pools)]
        return torch.cat(cells, 1)


def build_proxy(backbone: nn.Module, pooling, centers=None, *, heatmap_size=None, verified=None):
    """The proxy of ``backbone`` under per-keypoint cell pooling.

    Parameters
    ----------
    backbone : nn.Module
        Outputs ``(B, K, H, W)``.
    pooling : sequence of (PoolParams, PoolParams)
        One (horizontal, vertical) pair per keypoint, e.g. from
        :func:`kpstudy.models.pooling.keypoint_pooling`.
    centers : array_like of int, shape (K, 2), optional
        Nominal keypoints ``(u, v)`` in heatmap pixels: they fix the target cells and spec.
    heatmap_size : (int, int), optional
        ``(H, W)``; default ``(backbone.heatmap_size,) * 2``.
    verified : sequence of bool, optional
        Keypoints to verify (default all); the others get no spec rows.

    Returns
    -------
    KeypointProxy
        With ``index_map``, ``target_cells`` and ``spec``.

    Examples
    --------
    >>> from kpstudy.models.pooling import keypoint_pooling
    >>> proxy = build_proxy(nn.Identity(), keypoint_pooling([(4, 0)], [(1, 0)], (2, 10)),
    ...                     [(4, 0)], heatmap_size=(2, 10))
    >>> proxy.target_cells, proxy.index_map.shape
    ([1], (8, 2))
    """
    if heatmap_size is None:
        if not hasattr(backbone, "heatmap_size"):
            raise ValueError("heatmap_size: expected (H, W) for a backbone without .heatmap_size")
        heatmap_size = (backbone.heatmap_size, backbone.heatmap_size)
    H, W = (operator.index(s) for s in heatmap_size)
    pooling = list(pooling)
    if not pooling:
        raise ValueError("pooling: expected one (horizontal, vertical) pair per keypoint, got none")
    pools = []
    for k, pair in enumerate(pooling):
        if len(pair) != 2:
            raise ValueError(f"pooling[{k}]: expected a (horizontal, vertical) pair, got {pair!r}")
        pools.append(CellAvgPool2d(pair[1], pair[0], H, W))
    targets = None
    if centers is not None:
        centers = np.asarray(centers)
        if centers.shape != (len(pools), 2) or centers.dtype.kind not in "iu":
            raise ValueError(
                f"centers: expected ({len(pools)}, 2) integer heatmap pixels, "
                f"got {centers.dtype} {centers.shape}"
            )
        targets = []
        for k, ((u, v), pool) in enumerate(zip(centers.tolist(), pools)):
            if not (0 <= u < W and 0 <= v < H):
                raise ValueError(f"centers[{k}]: expected a pixel inside ({H}, {W}), got {(u, v)}")
            targets.append(cell_index(v, pool.params_v) * pool.n_h + cell_index(u, pool.params_h))
    return KeypointProxy(backbone, pools, targets, verified)
