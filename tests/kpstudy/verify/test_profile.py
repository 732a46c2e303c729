"""The per-node bound profile: soundness at every node, exactness where it must be exact,
CROWN pulled back from an inner node, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from kpstudy.verify import Box, ConvexHull, Parallelotope, bound_profile, output_bounds
from kpstudy.verify import bounds as B
from kpstudy.verify.graph import trace
from tests.helpers.verify_nets import MixedNet, hull_vertices


@pytest.mark.parametrize("n", [1, 3, 5])
@pytest.mark.parametrize("method", ["ibp", "forward", "zonotope"])
def test_every_node_contains_its_samples(n, method):
    net = MixedNet(seed=10 + n)
    V = hull_vertices(n, n, (2, 8, 8))
    for s in (ConvexHull(V), Parallelotope(V), Box(V.min(0).values, V.max(0).values)):
        rows = bound_profile(net, s, method=method, samples=400, crown_rows=6, seed=n)
        assert len(rows) == len(trace(net, V[:1]).nodes) - 1
        for r in rows:
            assert r["contained"], (type(s).__name__, r)
            if r["varying"]:
                assert r["ratio_median"] >= 1 - 1e-3, r
                assert r["ratio_total"] >= 1 - 1e-3, r
            if r["op"] == "ReLU":
                assert r["unstable_bound"] >= r["unstable_sampled"]
        # The last node's widths are output_bounds' (the profile runs the same bounds).
        lo, hi = output_bounds(net, s, method)
        assert math.isclose(rows[-1]["bound_width_max"], float((hi - lo).max()), rel_tol=1e-5)
        assert any("crown_ratio_median" in r for r in rows)


def test_forward_is_exact_on_a_linear_network_and_ibp_is_not():
    net = nn.Sequential(nn.Conv2d(2, 3, 3), nn.Flatten(), nn.Linear(3 * 6 * 6, 4)).double().eval()
    hull = ConvexHull(hull_vertices(0, 3, (2, 8, 8), dtype=torch.float64))
    forward = bound_profile(net, hull, samples=200)
    ibp = bound_profile(net, hull, method="ibp", samples=200)
    # Uniform samples do not reach a linear map's extremes (the vertices) exactly: the
    # corners added to the samples do.
    assert all(abs(r["ratio_median"] - 1.0) < 1e-9 for r in forward)
    assert all(abs(r["ratio_total"] - 1.0) < 1e-9 for r in forward)
    assert ibp[-1]["ratio_median"] > 1.5 and ibp[-1]["ratio_total"] > 1.5


def test_crown_from_an_inner_node_equals_crown_on_the_truncated_network():
    torch.manual_seed(0)
    layers = [nn.Conv2d(2, 4, 3, padding=1), nn.ReLU(), nn.Conv2d(4, 4, 3, padding=1)]
    net = nn.Sequential(*layers, nn.ReLU(), nn.Flatten(), nn.Linear(4 * 8 * 8, 3)).eval()
    head = nn.Sequential(*layers).eval()
    hull = ConvexHull(hull_vertices(2, 2, (2, 8, 8)))
    pick = torch.tensor([0, 17, 100, 255])
    none = torch.full_like(pick, -1)
    results = []
    for model, start in ((net, 3), (head, -1)):
        graph = trace(model, hull.vertices[:1])
        region = hull.region(hull.root(), graph.dtype)
        with torch.no_grad():
            _, state = B.propagate(graph, region)
            results.append(
                [
                    B.backward(graph, region, state, *rows, start=start)
                    for rows in ((pick, none), (none, pick))
                ]
            )
    for inner, truncated in zip(*results):
        torch.testing.assert_close(inner, truncated)


@pytest.mark.parametrize("method", ["ibp", "forward", "zonotope"])
def test_a_start_depth_bounds_the_union_of_its_nodes(method):
    net = MixedNet(seed=4)
    hull = ConvexHull(hull_vertices(4, 3, (2, 8, 8)))
    root = bound_profile(net, hull, method=method, samples=300)
    split = bound_profile(net, hull, method=method, samples=300, depth=1)
    box = Box(hull.vertices.min(0).values, hull.vertices.max(0).values)
    assert all(r["contained"] for r in bound_profile(net, box, method=method, depth=3))
    halves = [
        bound_profile(net, ConvexHull(hull.image(node, torch.float32)), method=method, samples=50)
        for node in hull.split(hull.root())
    ]
    for i, row in enumerate(split):
        assert row["contained"], row
        # The union holds each half's bounds.
        widest_half = max(h[i]["bound_width_max"] for h in halves)
        assert row["bound_width_max"] >= widest_half * (1 - 1e-5)
        if method == "ibp":  # intervals shrink with their input
            assert row["bound_width_max"] <= root[i]["bound_width_max"] * (1 + 1e-5)
    assert split[-1]["ratio_median"] < root[-1]["ratio_median"]


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"method": "crown"}, "method"),
        ({"samples": 0}, "samples"),
        ({"crown_rows": -1}, "crown_rows"),
        ({"crown_rows": True}, "crown_rows"),
        ({"chunk": 0}, "chunk"),
        ({"depth": -1}, "depth"),
        ({"depth": True}, "depth"),
        ({"depth": 2, "crown_rows": 3}, "crown_rows"),
    ],
)
def test_bad_arguments_are_named(kwargs, name):
    net = MixedNet(seed=0)
    hull = ConvexHull(hull_vertices(0, 2, (2, 8, 8)))
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        bound_profile(net, hull, **kwargs)
