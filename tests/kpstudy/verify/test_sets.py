"""kpstudy.verify.sets: input sets (points, membership, splits)."""

from __future__ import annotations

import math

import pytest
import torch

from kpstudy.verify import Box, ConvexHull, Parallelotope
from tests.helpers.verify_nets import hull_vertices


@pytest.mark.parametrize("n", [1, 2, 5])
def test_hull_points_map_and_stay_inside(n):
    V = hull_vertices(n, n, (2, 3, 3), dtype=torch.float64)
    hull = ConvexHull(V)
    for kind in ("dirichlet", "vertices", "edges"):
        lam = hull.sample(500, 0, kind)
        assert hull.contains_lambda(lam, tol=1e-12).all()
    lam = hull.sample(5, 1)
    weights = torch.cat([1 - lam.sum(1, keepdim=True), lam], 1)
    expected = torch.einsum("bv,v...->b...", weights, V)
    torch.testing.assert_close(hull.image(lam), expected)
    assert hull.contains(expected[0])
    assert not hull.contains(V[0] + 2 * (V[1] - V[0]))  # on the line, past a vertex


def test_parallelotope_is_a_superset_with_points_outside_the_hull():
    V = hull_vertices(0, 2, (4,), dtype=torch.float64)
    par, hull = Parallelotope(V), ConvexHull(V)
    lam = par.sample(4000, 0)
    outside = ~hull.contains_lambda(lam)
    assert outside.float().mean() == pytest.approx(0.5, abs=0.05)  # 1 − 1/n! for n = 2
    assert par.contains_lambda(hull.sample(100, 1)).all()


def test_simplex_split_children_cover_the_parent_exactly():
    hull = ConvexHull(hull_vertices(0, 3, (5,), dtype=torch.float64))
    nodes = hull.root()
    for _ in range(3):
        nodes = hull.split(nodes)
    assert len(nodes) == 8
    # every sampled λ lies in exactly one child (up to shared faces), volumes add up
    lam = hull.sample(2000, 3)
    inside = torch.stack([_in_simplex(lam, v) for v in nodes], 1)
    assert (inside.sum(1) >= 1).all()
    vols = torch.stack([_volume(v) for v in nodes])
    assert vols.sum().item() == pytest.approx(1 / math.factorial(3))


def _in_simplex(lam, verts, tol=1e-9):
    A = torch.cat([verts.T, torch.ones(1, len(verts), dtype=verts.dtype)])
    b = torch.cat([lam.T, torch.ones(1, len(lam), dtype=lam.dtype)])
    w = torch.linalg.solve(A, b)
    return (w >= -tol).all(0)


def _volume(verts):
    return torch.linalg.det(verts[1:] - verts[0]).abs() / math.factorial(verts.shape[1])


def test_cube_and_box_splits_halve_the_longest_side():
    par = Parallelotope(hull_vertices(0, 2, (4,), dtype=torch.float64))
    kids = par.split(par.root())
    widths = kids[:, 1] - kids[:, 0]
    assert sorted(widths.prod(1).tolist()) == [0.5, 0.5]
    box = Box(torch.zeros(3), torch.tensor([1.0, 4.0, 2.0]))
    kids = box.split(box.root())
    torch.testing.assert_close(kids[0, 1], torch.tensor([1.0, 2.0, 2.0]))
    torch.testing.assert_close(kids[1, 0], torch.tensor([0.0, 2.0, 0.0]))


def test_box_samples_and_membership():
    box = Box(-torch.ones(2, 2), torch.ones(2, 2))
    for kind in ("dirichlet", "vertices", "edges"):
        assert box.contains_point(box.sample(100, 0, kind)).all()
    assert not box.contains(torch.full((2, 2), 1.5))
    with pytest.raises(ValueError, match="upper: expected upper >= lower"):
        Box(torch.ones(2), torch.zeros(2))
    with pytest.raises(ValueError, match="upper: expected the shape of lower"):
        Box(torch.ones(2), torch.ones(3))
