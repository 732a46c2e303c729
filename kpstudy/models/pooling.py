"""Per-keypoint average pooling: the proxy model's cells and its class ``c_k``.

A keypoint's cell on each axis is an integer pixel range ``[lo, hi]`` (paper §6.3,
docs/design.md §4.4): the paper's ``[c - dv, c + dv]`` around the keypoint's heatmap pixel
``c`` (:func:`pooling_params`), or any range, e.g. one chosen from the exact keypoint
(:func:`cell_params`). The axis gets an average pooling with ``kernel = stride = hi - lo + 1``
and a zero padding ``pad_before = (-lo) mod stride`` so that one pooling window (a *cell*)
is exactly ``[lo, hi]``. ``pad_after`` completes the last window, so every real pixel lies
in exactly one cell and ``0 <= pad < stride`` on both sides. Border cells that overhang the image
average only the real pixels they cover: the pooled map is rescaled per cell by
``kernel area / real pixels``. The cell holding the keypoint is its class ``c_k``; any argmax
inside it is a keypoint error within ``dv`` on that axis.

The proxy compares cell *averages*. Between full cells, an ideal Gaussian peak
wins exactly while it lies in its cell; next to a partial border cell it
need not: a 1-pixel border cell can beat the peak's 9-pixel cell, and on logits a partial
target cell can keep winning after the peak has left it (tests/kpstudy/models/test_proxy.py).

Pixels are integers ``0 .. size - 1`` (pixel centres on integers); ``(u, v)`` = (column, row).
"""

from __future__ import annotations

import operator
from typing import NamedTuple

import numpy as np
import torch
from torch import nn
from torch.fx._symbolic_trace import is_fx_symbolic_tracing

from kpstudy.verify.ops import cell_pool


class PoolParams(NamedTuple):
    """Average pooling along one axis: window length, step and zero padding (all ints)."""

    kernel: int
    stride: int
    pad_before: int
    pad_after: int


def pooling_params(center, dv, size) -> PoolParams:
    """Pooling along one axis that puts one cell exactly on ``[center - dv, center + dv]``.

    Parameters
    ----------
    center : int
        The keypoint's heatmap pixel on this axis, in ``[0, size)``.
    dv : int
        Allocated tolerance in pixels, ``>= 0``.
    size : int
        Heatmap length along this axis, ``>= 1``.

    Returns
    -------
    PoolParams
        ``kernel = stride = 2 dv + 1``, ``pad_before = (dv - center) mod stride`` and
        ``pad_after`` such that ``size + pad_before + pad_after`` is a multiple of the stride.

    Examples
    --------
    >>> p = pooling_params(4, 1, 10)
    >>> p
    PoolParams(kernel=3, stride=3, pad_before=0, pad_after=2)
    >>> cell_bounds(cell_index(4, p), p, 10)
    (3, 5)
    """
    return _axis_params(center, dv, size, ("center", "dv", "size"))


def cell_params(lo, hi, size) -> PoolParams:
    """Pooling along one axis that puts one cell exactly on ``[lo, hi]``.

    Parameters
    ----------
    lo, hi : int
        First and last pixel of the cell, ``lo <= hi``; the cell meets ``[0, size)``.
    size : int
        Axis length, ``>= 1``.

    Examples
    --------
    >>> p = cell_params(3, 6, 10)
    >>> p
    PoolParams(kernel=4, stride=4, pad_before=1, pad_after=1)
    >>> [cell_bounds(i, p, 10) for i in range(num_cells(p, 10))]
    [(0, 2), (3, 6), (7, 9)]
    """
    return _range_params(lo, hi, size, ("lo", "hi", "size"))


def num_cells(params: PoolParams, size) -> int:
    """Number of cells along an axis of length ``size`` pooled with ``params``.

    Examples
    --------
    >>> num_cells(pooling_params(4, 1, 10), 10)
    4
    """
    params, size = _check_params(params, size)
    return (size + params.pad_before + params.pad_after) // params.stride


def cell_index(pixel, params: PoolParams):
    """Index of the cell holding ``pixel``: ``(pixel + pad_before) // stride``.

    Parameters
    ----------
    pixel : int or array_like of int
        Pixel coordinate(s) on this axis; any shape.
    params : PoolParams

    Returns
    -------
    int or numpy.ndarray
        An int for an int ``pixel``, else an integer array of ``pixel``'s shape.

    Examples
    --------
    >>> p = pooling_params(4, 1, 10)
    >>> cell_index(4, p), cell_index(np.arange(10), p).tolist()
    (1, [0, 0, 0, 1, 1, 1, 2, 2, 2, 3])
    """
    params = _check_params(params)
    if isinstance(pixel, bool | np.bool_):
        raise ValueError(f"pixel: expected an integer or an integer array, got {pixel!r}")
    if isinstance(pixel, int | np.integer):
        return (int(pixel) + params.pad_before) // params.stride
    a = np.asarray(pixel)
    if a.dtype.kind not in "iu":
        raise ValueError(f"pixel: expected an integer or an integer array, got dtype {a.dtype}")
    return (a.astype(np.int64) + params.pad_before) // params.stride


def cell_bounds(index, params: PoolParams, size) -> tuple[int, int]:
    """First and last real pixel of cell ``index`` (the window clipped to ``[0, size - 1]``).

    Examples
    --------
    >>> p = pooling_params(4, 1, 10)
    >>> [cell_bounds(i, p, 10) for i in range(num_cells(p, 10))]
    [(0, 2), (3, 5), (6, 8), (9, 9)]
    """
    n = num_cells(params, size)
    index = _int(index, "index", 0, n, f"an integer cell index in [0, {n})")
    first = index * params.stride - params.pad_before
    return max(first, 0), min(first + params.stride - 1, int(size) - 1)


class CellAvgPool2d(nn.Module):
    """Average of the real pixels of each cell of one heatmap channel (exactly linear).

    ``forward`` is ``kpstudy.verify.ops.cell_pool()``: ``F.pad(x, pad)`` (zeros),
    ``F.avg_pool2d(kernel_size)``, ``* scale``; the verifier traces it as that function.

    Parameters
    ----------
    params_v, params_h : PoolParams
        Pooling of the rows (vertical, height axis) and of the columns (horizontal, width).
    size_v, size_h : int
        Heatmap height ``H`` and width ``W``.

    Attributes
    ----------
    pad : tuple of int
        ``(left, right, top, bottom)`` as :func:`torch.nn.functional.pad` takes it.
    kernel_size, stride : tuple of int
        ``(k_v, k_h)`` and ``(s_v, s_h)``.
    scale : torch.Tensor
        Buffer ``(n_v, n_h)``, float64: ``k_v k_h / (real pixels in the cell)``; ``forward``
        casts it to the input's dtype.
    n_v, n_h : int
        Number of cells along rows and columns.

    Notes
    -----
    Shapes: input ``(B, 1, H, W)`` → output ``(B, 1, n_v, n_h)`` (channel dim kept);
    input ``(B, H, W)`` → output ``(B, n_v, n_h)``.

    Examples
    --------
    >>> pool = CellAvgPool2d(pooling_params(4, 1, 10), pooling_params(0, 0, 2), 10, 2)
    >>> pool(torch.ones(1, 1, 10, 2)).shape
    torch.Size([1, 1, 4, 2])
    """

    scale: torch.Tensor

    def __init__(self, params_v: PoolParams, params_h: PoolParams, size_v, size_h) -> None:
        super().__init__()
        self.params_v, self.size_v = _check_params(params_v, size_v, ("params_v", "size_v"))
        self.params_h, self.size_h = _check_params(params_h, size_h, ("params_h", "size_h"))
        pv, ph = self.params_v, self.params_h
        self.pad = (ph.pad_before, ph.pad_after, pv.pad_before, pv.pad_after)
        self.kernel_size = (pv.kernel, ph.kernel)
        self.stride = (pv.stride, ph.stride)
        real_v, real_h = _real_counts(pv, self.size_v), _real_counts(ph, self.size_h)
        self.n_v, self.n_h = len(real_v), len(real_h)
        scale = (pv.kernel * ph.kernel) / np.outer(real_v, real_h).astype(np.float64)
        self.register_buffer("scale", torch.from_numpy(scale))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Pool ``x`` of shape ``(B, 1, H, W)`` or ``(B, H, W)`` into cell averages."""
        self._check_input(x)
        return cell_pool(x, self.pad, self.kernel_size, self.scale)

    def extra_repr(self) -> str:
        return (
            f"size=({self.size_v}, {self.size_h}), kernel_size={self.kernel_size}, "
            f"pad={self.pad}, cells=({self.n_v}, {self.n_h})"
        )

    def _check_input(self, x) -> None:
        if torch.jit.is_tracing() or is_fx_symbolic_tracing():  # shapes fixed by the example
            return
        hw = (self.size_v, self.size_h)
        expected = f"(B, 1, {hw[0]}, {hw[1]}) or (B, {hw[0]}, {hw[1]})"
        if not isinstance(x, torch.Tensor):
            raise ValueError(f"x: expected a torch.Tensor of shape {expected}, got {type(x)}")
        shape = tuple(x.shape)
        if not (
            (x.ndim == 4 and shape[1] == 1 and shape[2:] == hw) or (x.ndim == 3 and shape[1:] == hw)
        ):
            raise ValueError(f"x: expected shape {expected}, got {shape}")
        if not x.is_floating_point():
            raise ValueError(f"x: expected a floating-point tensor, got {x.dtype}")


def build_cell_pool(center_uv, dv_uv, heatmap_size) -> tuple[CellAvgPool2d, int]:
    """The pooling of one keypoint's heatmap channel and the keypoint's class ``c_k``.

    Parameters
    ----------
    center_uv : (int, int)
        Keypoint heatmap pixel ``(u, v)`` = (column, row).
    dv_uv : (int, int)
        Tolerances ``(dv_u, dv_v)``: horizontal (columns), vertical (rows).
    heatmap_size : (int, int)
        ``(H, W)``.

    Returns
    -------
    pool : CellAvgPool2d
        Output ``(B, 1, n_v, n_h)`` for input ``(B, 1, H, W)``.
    target : int
        Row-major flat index of the keypoint's cell in ``(n_v, n_h)``.

    Examples
    --------
    >>> pool, c_k = build_cell_pool((4, 0), (1, 0), (2, 10))
    >>> (pool.n_v, pool.n_h), c_k
    ((2, 4), 1)
    """
    u, v = _pair(center_uv, "center_uv")
    dv_u, dv_v = _pair(dv_uv, "dv_uv")
    H, W = _pair(heatmap_size, "heatmap_size")
    pv = _axis_params(v, dv_v, H, ("center_uv[1]", "dv_uv[1]", "heatmap_size[0]"))
    ph = _axis_params(u, dv_u, W, ("center_uv[0]", "dv_uv[0]", "heatmap_size[1]"))
    pool = CellAvgPool2d(pv, ph, operator.index(H), operator.index(W))
    target = cell_index(operator.index(v), pv) * pool.n_h + cell_index(operator.index(u), ph)
    return pool, target


def keypoint_cells(lo, hi, heatmap_size) -> list[tuple[PoolParams, PoolParams]]:
    """One (horizontal, vertical) pair of :func:`cell_params` per keypoint.

    Parameters
    ----------
    lo, hi : array_like of int, shape (K, 2)
        Each keypoint's cell ``[lo, hi]`` per axis ``(u, v)``, heatmap pixels.
    heatmap_size : (int, int)
        ``(H, W)``.

    Examples
    --------
    >>> horizontal, vertical = keypoint_cells([(3, 0)], [(6, 1)], (2, 10))[0]
    >>> horizontal, vertical.kernel
    (PoolParams(kernel=4, stride=4, pad_before=1, pad_after=1), 2)
    """
    return _per_keypoint(lo, hi, heatmap_size, ("lo", "hi"), _range_params)


def keypoint_pooling(centers, dv, heatmap_size) -> list[tuple[PoolParams, PoolParams]]:
    """One (horizontal, vertical) pair of :func:`pooling_params` per keypoint.

    Parameters
    ----------
    centers : array_like of int, shape (K, 2)
        Nominal keypoints ``(u, v)`` in heatmap pixels.
    dv : array_like of int, shape (K, 2)
        Tolerances ``(δu, δv)`` in heatmap pixels.
    heatmap_size : (int, int)
        ``(H, W)``.

    Examples
    --------
    >>> horizontal, vertical = keypoint_pooling([(4, 0)], [(1, 0)], (2, 10))[0]
    >>> horizontal
    PoolParams(kernel=3, stride=3, pad_before=0, pad_after=2)
    """
    return _per_keypoint(centers, dv, heatmap_size, ("centers", "dv"), _axis_params)


def _per_keypoint(first, second, heatmap_size, names, axis_params) -> list:
    """``[(axis_params(first[k][0], second[k][0], W), axis_params(…[1], H)) for k]`` with
    each argument named in its errors (``names``: those of ``first`` and ``second``)."""
    first = [_pair(x, f"{names[0]}[k]") for x in first]
    second = [_pair(x, f"{names[1]}[k]") for x in second]
    if len(first) != len(second):
        raise ValueError(
            f"{names[1]}: expected {len(first)} rows (one per keypoint), got {len(second)}"
        )
    H, W = _pair(heatmap_size, "heatmap_size")
    a, b = names
    return [
        (
            axis_params(u, su, W, (f"{a}[{k}][0]", f"{b}[{k}][0]", "heatmap_size[1]")),
            axis_params(v, sv, H, (f"{a}[{k}][1]", f"{b}[{k}][1]", "heatmap_size[0]")),
        )
        for k, ((u, v), (su, sv)) in enumerate(zip(first, second))
    ]


def _axis_params(center, dv, size, names: tuple[str, str, str]) -> PoolParams:
    """The cell ``[center - dv, center + dv]``, ``center`` a pixel of the axis."""
    size = _int(size, names[2], 1, None, "an integer >= 1")
    center = _int(center, names[0], 0, size, f"an integer pixel in [0, {size})")
    dv = _int(dv, names[1], 0, None, "an integer >= 0")
    return _range_params(center - dv, center + dv, size, names)


def _range_params(lo, hi, size, names: tuple[str, str, str]) -> PoolParams:
    """The cell ``[lo, hi]`` (it must meet ``[0, size)``)."""
    size = _int(size, names[2], 1, None, "an integer >= 1")
    lo = _int(lo, names[0], -(2**62), size, f"an integer pixel < {size}")
    hi = _int(hi, names[1], max(lo, 0), None, f"an integer >= max({names[0]}, 0)")
    stride = hi - lo + 1
    pad_before = (-lo) % stride
    n = -(-(size + pad_before) // stride)
    return PoolParams(stride, stride, pad_before, n * stride - size - pad_before)


def _real_counts(params: PoolParams, size: int) -> np.ndarray:
    """Real (non-padding) pixels in each cell, shape ``(n,)``."""
    n = (size + params.pad_before + params.pad_after) // params.stride
    first = np.arange(n) * params.stride - params.pad_before
    last = first + params.stride - 1
    return np.minimum(last, size - 1) - np.maximum(first, 0) + 1


def _check_params(params, size=None, names: tuple[str, str] = ("params", "size")):
    """``params`` as a consistent :class:`PoolParams`; with ``size``, also the checked size."""
    ok = (
        isinstance(params, PoolParams)
        and all(isinstance(p, int) and not isinstance(p, bool) for p in params)
        and params.kernel == params.stride >= 1
        and 0 <= params.pad_before < params.stride
        and 0 <= params.pad_after < params.stride
    )
    if not ok:
        raise ValueError(
            f"{names[0]}: expected a PoolParams from pooling_params or cell_params "
            f"(kernel == stride, 0 <= pads < stride), got {params!r}"
        )
    if size is None:
        return params
    size = _int(size, names[1], 1, None, "an integer >= 1")
    total = size + params.pad_before + params.pad_after
    if total % params.stride:
        raise ValueError(
            f"{names[1]}: expected the axis length {names[0]} was built for "
            f"(size + pads a multiple of {params.stride}), got {size}"
        )
    return params, size


def _int(x, name: str, lo: int, hi: int | None, expected: str) -> int:
    """``x`` as a Python int with ``lo <= x`` and ``x < hi`` (``hi=None``: no upper bound)."""
    if isinstance(x, bool | np.bool_):
        raise ValueError(f"{name}: expected {expected}, got {x!r}")
    try:
        i = operator.index(x)
    except TypeError as exc:
        raise ValueError(f"{name}: expected {expected}, got {x!r}") from exc
    if i < lo or (hi is not None and i >= hi):
        raise ValueError(f"{name}: expected {expected}, got {i}")
    return i


def _pair(x, name: str) -> tuple:
    try:
        items = tuple(x)
    except TypeError as exc:
        raise ValueError(f"{name}: expected a pair of integers, got {x!r}") from exc
    if len(items) != 2:
        raise ValueError(f"{name}: expected a pair of integers, got {x!r}")
    return items
