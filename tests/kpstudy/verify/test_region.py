"""kpstudy.verify.region: the bounds of a value over regions of the input set's domain,
exact against its vertices, with error symbols dense or in blocks."""

from __future__ import annotations

import itertools

import pytest
import torch

from kpstudy.verify import symbols
from kpstudy.verify.region import Region, domain_min

B, Q, SHAPE = 3, 4, (2, 3, 3)  # regions, rows (constant + 3 parameters), value shape


def vertices(domain: str, n: int = Q - 1) -> torch.Tensor:
    """The domain's vertices θ ``(V, n)``: where an affine function has its extremes."""
    if domain == "simplex":
        return torch.cat([torch.zeros(1, n), torch.eye(n)]).double()
    return torch.tensor(list(itertools.product([0.0, 1.0], repeat=n))).double()


def at(coeff: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``coeff[:, 0] + Σ_i coeff[:, i] θ_i`` at each θ: ``(V, B, *S)``."""
    return coeff[:, 0] + torch.einsum("vi,bi...->vb...", theta, coeff[:, 1:])


@pytest.mark.parametrize("domain", ["simplex", "cube"])
def test_the_domain_minimum_is_the_least_value_at_a_vertex(domain):
    a = torch.randn(B, Q, *SHAPE, dtype=torch.float64)
    torch.testing.assert_close(domain_min(a, domain), at(a, vertices(domain)).min(0).values)
    torch.testing.assert_close(domain_min(a, "point"), a[:, 0])
    torch.testing.assert_close(domain_min(a[:, :1], domain), a[:, 0])
    with pytest.raises(ValueError, match="^domain: expected 'simplex', 'cube' or 'point'"):
        domain_min(a, "ball")


@pytest.mark.parametrize("domain", ["simplex", "cube"])
def test_bounds_are_exact_over_the_domain_and_the_symbols(domain):
    """Lower ``mid − rad`` and upper ``mid + rad`` at their extreme vertices, moved by each
    symbol's full reach; the same with the symbols moved into the radius."""
    g = torch.Generator().manual_seed(0)
    mid = torch.randn(B, Q + 5, *SHAPE, generator=g, dtype=torch.float64)  # 5 symbols
    rad = torch.rand(B, Q, *SHAPE, generator=g, dtype=torch.float64)
    region = Region(mid, rad, domain)
    reach = mid[:, Q:].abs().sum(1)
    theta = vertices(domain)
    low, high = region.bounds()
    torch.testing.assert_close(low, at(mid[:, :Q] - rad, theta).min(0).values - reach)
    torch.testing.assert_close(high, at(mid[:, :Q] + rad, theta).max(0).values + reach)
    torch.testing.assert_close(region.reach(), reach)
    index = torch.tensor([0, 7, 7, 17])
    torch.testing.assert_close(region.symbols_at(index), mid[:, Q:].flatten(2)[..., index])
    loose = region.without_symbols()
    assert loose.mid.shape[1] == Q and isinstance(loose.reach(), float)
    for a, b in zip(loose.bounds(), (low, high)):
        torch.testing.assert_close(a, b)


def test_intervals_affine_inputs_and_selected_regions():
    lower = torch.randn(B, *SHAPE, dtype=torch.float64)
    upper = lower + torch.rand(B, *SHAPE, dtype=torch.float64)
    box = Region.interval(lower, upper)
    assert box.domain == "point" and box.batch == B
    for a, b in zip(box.bounds(), (lower, upper)):
        torch.testing.assert_close(a, b)
    for a, b in zip(box.to_interval().bounds(), (lower, upper)):
        torch.testing.assert_close(a, b)
    coeff = torch.randn(B, Q, *SHAPE, dtype=torch.float64)
    exact = Region.affine(coeff, "simplex")
    values = at(coeff, vertices("simplex"))
    torch.testing.assert_close(exact.bounds()[0], values.min(0).values)
    torch.testing.assert_close(exact.bounds()[1], values.max(0).values)
    rows = torch.tensor([2, 0])
    picked = exact.select(rows)
    assert picked.batch == 2
    torch.testing.assert_close(picked.bounds()[1], exact.bounds()[1][rows])
    mask = torch.tensor([False, True, False])
    torch.testing.assert_close(exact.select(mask).bounds()[0], exact.bounds()[0][mask])


def test_symbols_in_blocks_read_as_the_dense_stack():
    mu = torch.rand(B, *SHAPE, dtype=torch.float64) * (torch.rand(B, *SHAPE) < 0.5)
    mu[:, 0, 0, 0] = 1.0
    blocks = symbols.make(mu, Q)
    rows = Q + blocks[0].rows
    mid = torch.randn(B, Q, *SHAPE, dtype=torch.float64)
    rad = torch.rand(B, Q, *SHAPE, dtype=torch.float64)
    held = Region(mid, rad, "simplex", blocks, rows)
    dense = Region(symbols.dense(mid, blocks, rows), rad, "simplex")
    torch.testing.assert_close(held.reach(), dense.reach())
    for a, b in zip(held.bounds(), dense.bounds()):
        torch.testing.assert_close(a, b)
    index = torch.tensor([0, 5, 9, 17, 5])
    torch.testing.assert_close(held.symbols_at(index), dense.symbols_at(index))
    rows_kept = torch.tensor([1, 2])
    for a, b in zip(held.select(rows_kept).bounds(), dense.select(rows_kept).bounds()):
        torch.testing.assert_close(a, b)
