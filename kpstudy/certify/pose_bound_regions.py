"""Where each keypoint's argmax can go over a hull: the pose-bound method's regions.

:func:`search_regions` runs :func:`kpstudy.verify.reachable.reachable_argmax` on a backbone's
heatmaps (stride 1: the heatmap pixels themselves) or on a proxy that pools ``stride ×
stride`` cells around the rounded ground truth (``region_pooling()``), and
:func:`region_pixels` turns each keypoint's possible cells into heatmap pixels: a sound
superset of the pixels that are the argmax somewhere in the hull (docs/design.md §4.11).
``focus_cells()`` picks the cells a focused second search may still remove.

Shapes and units: a keypoint's *cells* are indices into its pooling grid (row-major,
``u`` fastest); its *pixels* are ``(n_k, 2)`` float64 heatmap pixels ``(u, v)``, sorted
by ``(u, v)``; ``centers`` are ``(K, 2)`` integer heatmap pixels.
"""

from __future__ import annotations

import numpy as np

from kpstudy.models.pooling import cell_bounds, keypoint_pooling, num_cells
from kpstudy.models.proxy import build_proxy
from kpstudy.verify import Regions, reachable_argmax

__all__ = ["region_pixels", "search_regions"]


def region_pooling(centers, stride: int, heatmap_size: int):
    """The stride-``stride`` cells around ``centers (K, 2)`` the region search bounds."""
    half = np.full_like(centers, (stride - 1) // 2)
    return keypoint_pooling(centers, half, (heatmap_size, heatmap_size))


def search_regions(
    backbone, hull, centers, stride: int, search: dict, focus=None, resume=None, witnesses=None
):
    """Possible pixels of each keypoint over ``hull``:
    :func:`~kpstudy.verify.reachable.reachable_argmax` on the stride-``stride`` proxy around
    ``centers (K, 2)`` (heatmap pixels) with ``search``'s keywords, ``focus``, ``resume``
    and ``witnesses`` (per keypoint, ``{cell: λ}``); the
    :class:`~kpstudy.verify.reachable.Regions` and each keypoint's pixels ``(n_k, 2)``. At
    stride 1 the proxy's cells are the heatmap pixels in the backbone's own order, so the
    backbone is searched itself: its output keeps the zonotope's error symbols in blocks
    that the search reads where it needs them."""
    hm = backbone.heatmap_size
    pooling = region_pooling(centers, stride, hm)
    if stride == 1:
        model, sizes = backbone, [hm * hm] * len(centers)
    else:
        model = build_proxy(backbone, pooling, centers).eval()
        sizes = model.spec.group_sizes
    regions = reachable_argmax(
        model, hull, sizes, focus=focus, resume=resume, witnesses=witnesses, **search
    )
    return regions, region_pixels(regions, pooling, hm)


def region_pixels(regions, pooling, heatmap_size: int) -> list[np.ndarray]:
    """Heatmap pixels ``(n_k, 2)`` as ``(u, v)`` of each keypoint's possible cells.

    ``pooling`` is the (horizontal, vertical) :class:`kpstudy.models.pooling.PoolParams` pair of
    each keypoint that the regions' proxy used; a cell contributes all its real pixels.
    """
    out = []
    for k, pair in enumerate(pooling):
        mask = np.zeros((heatmap_size, heatmap_size), dtype=bool)  # [u, v]
        for u0, u1, v0, v1 in _cell_boxes(regions.possible[k], pair, heatmap_size):
            mask[u0 : u1 + 1, v0 : v1 + 1] = True
        out.append(np.argwhere(mask).astype(np.float64).reshape(-1, 2))  # sorted by (u, v)
    return out


def _cell_boxes(cells, pair, heatmap_size: int) -> np.ndarray:
    """First and last real pixel ``(u0, u1, v0, v1)`` of each of ``cells`` (indices of the
    grid of the (horizontal, vertical) :class:`kpstudy.models.pooling.PoolParams` ``pair``),
    ``(len(cells), 4)``."""
    horizontal, vertical = pair
    n_h, n_v = num_cells(horizontal, heatmap_size), num_cells(vertical, heatmap_size)
    u_bounds = np.array([cell_bounds(i, horizontal, heatmap_size) for i in range(n_h)])
    v_bounds = np.array([cell_bounds(i, vertical, heatmap_size) for i in range(n_v)])
    cells = np.asarray(cells, dtype=np.int64).reshape(-1)
    return np.concatenate([u_bounds[cells % n_h], v_bounds[cells // n_h]], axis=1)


def focus_cells(regions, pooling, heatmap_size: int, involved) -> list[np.ndarray]:
    """Per keypoint, its possible cells (indices of ``regions.possible[k]``'s group) that
    hold a pixel of ``involved[k]`` (bool over :func:`region_pixels`' pixels) and have no
    witness: the cells a further split may remove."""
    out = []
    pixels = region_pixels(regions, pooling, heatmap_size)
    for k, pair in enumerate(pooling):
        bad = np.zeros((heatmap_size, heatmap_size), dtype=bool)  # [u, v]
        u, v = pixels[k][involved[k]].astype(np.int64).T
        bad[u, v] = True
        cells = np.asarray(regions.possible[k], dtype=np.int64)
        boxes = _cell_boxes(cells, pair, heatmap_size)
        out.append(
            np.array(
                [
                    int(c)
                    for c, (u0, u1, v0, v1) in zip(cells, boxes)
                    if c not in regions.witnesses[k] and bad[u0 : u1 + 1, v0 : v1 + 1].any()
                ],
                dtype=np.int64,
            )
        )
    return out


def pixel_grid(heatmap_size: int) -> np.ndarray:
    """Every heatmap pixel ``(u, v)``, sorted, ``(heatmap_size², 2)``."""
    u, v = np.meshgrid(np.arange(heatmap_size), np.arange(heatmap_size), indexing="ij")
    return np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)


def unsearched_regions(heatmap_size: int) -> Regions:
    """The regions of a search that was skipped: every pixel possible, none reached."""
    size = heatmap_size * heatmap_size
    return Regions([size], [np.arange(size)], [{}], 0.0, 0, {"stopped": None})
