"""Tests of kpstudy.models.pooling: cell geometry, the pooling op, and the keypoint class."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from kpstudy.models import pooling
from kpstudy.models.pooling import (
    CellAvgPool2d,
    PoolParams,
    build_cell_pool,
    cell_bounds,
    cell_index,
    num_cells,
    pooling_params,
)


@st.composite
def axes(draw, max_size: int = 300):
    """(center, dv, size) with size in [1, max_size], center in [0, size), dv in [0, 2 size]."""
    size = draw(st.integers(1, max_size))
    center = draw(st.integers(0, size - 1))
    dv = draw(st.integers(0, 2 * size))
    return center, dv, size


def brute_cells(center: int, dv: int, size: int) -> list[tuple[int, int]]:
    """Cells by definition: windows [center - dv + k s, center + dv + k s] that meet the axis."""
    s = 2 * dv + 1
    cells = []
    for k in range(-(size // s) - 2, size // s + 3):
        first, last = center - dv + k * s, center + dv + k * s
        if last >= 0 and first <= size - 1:
            cells.append((max(first, 0), min(last, size - 1)))
    return cells


def brute_pool(x: np.ndarray, cells_v, cells_h) -> np.ndarray:
    """Mean of the real pixels of each cell of a (H, W) array."""
    out = np.empty((len(cells_v), len(cells_h)))
    for i, (a, b) in enumerate(cells_v):
        for j, (c, d) in enumerate(cells_h):
            out[i, j] = x[a : b + 1, c : d + 1].mean()
    return out


def gaussian(center_uv, sigma_uv, heatmap_size) -> np.ndarray:
    """Separable Gaussian (H, W) peaked at (u, v) = (column, row)."""
    H, W = heatmap_size
    gu = np.exp(-0.5 * ((np.arange(W) - center_uv[0]) / sigma_uv[0]) ** 2)
    gv = np.exp(-0.5 * ((np.arange(H) - center_uv[1]) / sigma_uv[1]) ** 2)
    return np.outer(gv, gu)


@settings(max_examples=300, deadline=None)
@given(axes())
def test_pooling_params_properties(axis):
    center, dv, size = axis
    p = pooling_params(center, dv, size)
    assert all(type(f) is int for f in p)
    assert p.kernel == p.stride == 2 * dv + 1
    assert 0 <= p.pad_before < p.stride and 0 <= p.pad_after < p.stride
    assert (size + p.pad_before + p.pad_after) % p.stride == 0
    n = num_cells(p, size)
    assert n * p.stride == size + p.pad_before + p.pad_after

    # The keypoint's cell is exactly [center - dv, center + dv] on the real pixels.
    k = cell_index(center, p)
    assert cell_bounds(k, p, size) == (max(center - dv, 0), min(center + dv, size - 1))

    # Every pixel lies in exactly one cell, and cell_index agrees with cell_bounds.
    bounds = [cell_bounds(i, p, size) for i in range(n)]
    cover = np.zeros(size, dtype=int)
    for first, last in bounds:
        assert 0 <= first <= last <= size - 1
        cover[first : last + 1] += 1
    assert np.all(cover == 1)
    idx = cell_index(np.arange(size), p)
    assert idx.shape == (size,) and idx.dtype.kind == "i"
    for i, (first, last) in enumerate(bounds):
        assert np.all(idx[first : last + 1] == i)
    assert bounds == brute_cells(center, dv, size)


def test_pooling_params_examples():
    assert pooling_params(4, 1, 10) == PoolParams(3, 3, 0, 2)
    assert pooling_params(0, 2, 10) == PoolParams(5, 5, 2, 3)
    assert pooling_params(0, 0, 1) == PoolParams(1, 1, 0, 0)
    assert pooling_params(0, 2, 1) == PoolParams(5, 5, 2, 2)
    assert pooling_params(np.int64(7), np.int32(1), np.int16(9)) == pooling_params(7, 1, 9)


def test_cell_index_scalar_and_array():
    p = pooling_params(4, 1, 10)
    assert cell_index(4, p) == 1 and type(cell_index(4, p)) is int
    assert cell_index(np.int32(9), p) == 3
    grid = np.array([[0, 3], [6, 9]], dtype=np.uint8)
    np.testing.assert_array_equal(cell_index(grid, p), [[0, 1], [2, 3]])


@st.composite
def pools(draw):
    """(center_uv, dv_uv, heatmap_size) with small, non-square heatmaps."""
    cv, dvv, H = draw(axes(max_size=24))
    cu, dvu, W = draw(axes(max_size=24))
    return (cu, cv), (dvu, dvv), (H, W)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@settings(max_examples=60, deadline=None)
@given(case=pools(), seed=st.integers(0, 2**32 - 1))
def test_cell_avg_pool_matches_brute_force(dtype, case, seed):
    (u, v), (dvu, dvv), (H, W) = case
    pool, _ = build_cell_pool((u, v), (dvu, dvv), (H, W))
    x = np.random.default_rng(seed).normal(size=(3, H, W))
    expected = np.stack(
        [brute_pool(xi, brute_cells(v, dvv, H), brute_cells(u, dvu, W)) for xi in x]
    )

    y4 = pool(torch.tensor(x, dtype=dtype).unsqueeze(1))
    y3 = pool(torch.tensor(x, dtype=dtype))
    assert y4.shape == (3, 1, pool.n_v, pool.n_h) and y4.dtype == dtype
    assert y3.shape == (3, pool.n_v, pool.n_h) and y3.dtype == dtype
    rtol, atol = (1e-12, 1e-12) if dtype == torch.float64 else (1e-6, 1e-6)
    np.testing.assert_allclose(y4[:, 0].double().numpy(), expected, rtol=rtol, atol=atol)
    np.testing.assert_allclose(y3.double().numpy(), expected, rtol=rtol, atol=atol)


def test_cell_avg_pool_attributes_are_the_three_steps():
    pv, ph = pooling_params(3, 2, 11), pooling_params(0, 1, 7)
    pool = CellAvgPool2d(pv, ph, 11, 7)
    assert pool.pad == (ph.pad_before, ph.pad_after, pv.pad_before, pv.pad_after)
    assert pool.kernel_size == (5, 3) and pool.stride == (5, 3)
    assert (pool.n_v, pool.n_h) == (num_cells(pv, 11), num_cells(ph, 7))
    assert "scale" in dict(pool.named_buffers())
    x = torch.randn(2, 1, 11, 7, dtype=torch.float64)
    manual = (
        torch.nn.functional.avg_pool2d(
            torch.nn.functional.pad(x, pool.pad), pool.kernel_size, pool.stride
        )
        * pool.scale
    )
    torch.testing.assert_close(pool(x), manual, rtol=0, atol=0)
    # A constant map pools to the same constant, border cells included.
    torch.testing.assert_close(
        pool(torch.full_like(x, 2.5)), torch.full((2, 1, 3, 3), 2.5).double()
    )


@settings(max_examples=40, deadline=None)
@given(case=pools(), seed=st.integers(0, 2**32 - 1))
def test_cell_avg_pool_is_linear(case, seed):
    pool, _ = build_cell_pool(*case)
    H, W = case[2]
    rng = np.random.default_rng(seed)
    x, y = (torch.tensor(rng.normal(size=(2, 1, H, W))) for _ in range(2))
    a, b = rng.normal(size=2) * 10
    torch.testing.assert_close(
        pool(a * x + b * y), a * pool(x) + b * pool(y), rtol=1e-12, atol=1e-12
    )


def test_build_cell_pool_axis_order():
    # u is the column (width W = 50), v the row (height H = 20).
    pool, target = build_cell_pool((40, 3), (1, 4), (20, 50))
    assert pool.params_h == pooling_params(40, 1, 50)
    assert pool.params_v == pooling_params(3, 4, 20)
    assert (pool.size_v, pool.size_h) == (20, 50)
    row, col = divmod(target, pool.n_h)
    assert cell_bounds(row, pool.params_v, 20) == (0, 7)
    assert cell_bounds(col, pool.params_h, 50) == (39, 41)
    assert pool(torch.zeros(1, 1, 20, 50)).shape == (1, 1, pool.n_v, pool.n_h)


def _adjacent_cells_full(index: int, params: PoolParams, size: int) -> bool:
    n = num_cells(params, size)
    for j in (index - 1, index + 1):
        if 0 <= j < n:
            first, last = cell_bounds(j, params, size)
            if last - first + 1 < params.stride:
                return False
    return True


@settings(max_examples=80, deadline=None)
@given(
    case=pools(),
    sigma=st.tuples(st.floats(0.3, 8.0), st.floats(0.3, 8.0)),
    frac=st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
)
def test_gaussian_peak_lands_in_target_cell(case, sigma, frac):
    (u, v), (dvu, dvv), (H, W) = case
    pool, target = build_cell_pool((u, v), (dvu, dvv), (H, W))

    # A symmetric peak on the keypoint: the pooled argmax is the keypoint's class.
    y = pool(torch.tensor(gaussian((u, v), sigma, (H, W)))[None, None])
    assert int(torch.argmax(y.flatten())) == target

    # A peak moved by at most dv on each axis stays inside the target cell's pixels.
    pu = int(np.clip(u + round(frac[0] * dvu), 0, W - 1))
    pv = int(np.clip(v + round(frac[1] * dvv), 0, H - 1))
    row, col = divmod(target, pool.n_h)
    first_v, last_v = cell_bounds(row, pool.params_v, H)
    first_h, last_h = cell_bounds(col, pool.params_h, W)
    assert first_v <= pv <= last_v and first_h <= pu <= last_h
    assert cell_index(pv, pool.params_v) * pool.n_h + cell_index(pu, pool.params_h) == target

    # With full-width neighbours (no clipped border cell beside it), the moved peak still
    # pools to the target class.
    if _adjacent_cells_full(row, pool.params_v, H) and _adjacent_cells_full(col, pool.params_h, W):
        y = pool(torch.tensor(gaussian((pu, pv), sigma, (H, W)))[None, None])
        assert int(torch.argmax(y.flatten())) == target


def test_peak_outside_tolerance_leaves_target_cell():
    pool, target = build_cell_pool((10, 10), (2, 2), (32, 32))
    y = pool(torch.tensor(gaussian((13, 10), (1.0, 1.0), (32, 32)))[None, None])
    assert int(torch.argmax(y.flatten())) == target + 1


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((-1, 1, 10), "center"),
        ((10, 1, 10), "center"),
        ((1.5, 1, 10), "center"),
        ((np.float64(2.0), 1, 10), "center"),
        ((True, 1, 10), "center"),
        ((2, -1, 10), "dv"),
        ((2, 1.0, 10), "dv"),
        ((2, False, 10), "dv"),
        ((0, 1, 0), "size"),
        ((0, 1, -3), "size"),
        ((0, 1, "10"), "size"),
    ],
)
def test_pooling_params_rejects_bad_arguments(args, name):
    with pytest.raises(ValueError, match=rf"^{name}: expected"):
        pooling_params(*args)


def test_helpers_reject_bad_arguments():
    p = pooling_params(4, 1, 10)
    with pytest.raises(ValueError, match=r"^params: expected"):
        num_cells((3, 3, 0, 2), 10)
    with pytest.raises(ValueError, match=r"^params: expected"):
        num_cells(PoolParams(3, 5, 0, 2), 10)
    with pytest.raises(ValueError, match=r"^size: expected"):
        num_cells(p, 11)
    with pytest.raises(ValueError, match=r"^index: expected"):
        cell_bounds(4, p, 10)
    with pytest.raises(ValueError, match=r"^index: expected"):
        cell_bounds(-1, p, 10)
    with pytest.raises(ValueError, match=r"^pixel: expected"):
        cell_index(np.array([1.0, 2.0]), p)
    with pytest.raises(ValueError, match=r"^pixel: expected"):
        cell_index(True, p)


def test_module_rejects_bad_arguments():
    pv, ph = pooling_params(3, 1, 8), pooling_params(2, 0, 6)
    with pytest.raises(ValueError, match=r"^size_v: expected"):
        CellAvgPool2d(pv, ph, 9, 6)
    with pytest.raises(ValueError, match=r"^params_h: expected"):
        CellAvgPool2d(pv, None, 8, 6)
    pool = CellAvgPool2d(pv, ph, 8, 6)
    for bad in (
        torch.zeros(2, 2, 8, 6),
        torch.zeros(2, 1, 6, 8),
        torch.zeros(8, 6),
        torch.zeros(1, 1, 1, 8, 6),
        torch.zeros(2, 8, 7),
        torch.zeros(2, 1, 8, 6, dtype=torch.int64),
        np.zeros((2, 1, 8, 6)),
    ):
        with pytest.raises(ValueError, match=r"^x: expected"):
            pool(bad)


@pytest.mark.parametrize(
    ("args", "name"),
    [
        (((5, 8), (1, 1), (8, 8)), r"center_uv\[1\]"),
        (((8, 5), (1, 1), (20, 8)), r"center_uv\[0\]"),
        (((1, 1), (-1, 1), (8, 8)), r"dv_uv\[0\]"),
        (((1, 1), (1, 1.5), (8, 8)), r"dv_uv\[1\]"),
        (((1, 1), (1, 1), (0, 8)), r"heatmap_size\[0\]"),
        (((1, 2, 3), (1, 1), (8, 8)), "center_uv"),
        (((1, 1), 1, (8, 8)), "dv_uv"),
        (((1, 1), (1, 1), 8), "heatmap_size"),
    ],
)
def test_build_cell_pool_rejects_bad_arguments(args, name):
    with pytest.raises(ValueError, match=rf"^{name}: expected"):
        build_cell_pool(*args)


def test_docstring_examples():
    result = doctest.testmod(pooling, extraglobs={"np": np, "torch": torch})
    assert result.attempted > 0 and result.failed == 0
