"""benchmarks/relaxation_levers.py: its two alternative ReLU relaxations are sound — DeepZ
at any slope in [0, 1] and DeepZ on CROWN-tightened pre-activation bounds bound every
layer's sampled values (random points, the hull's vertices and points on its edges) —
and the tightening never adds an unstable neuron."""

import pytest
import torch

from benchmarks.relaxation_levers import (
    Recorded,
    Slopes,
    Tightened,
    node_at,
    relu_rules,
)
from kpstudy.verify import ConvexHull, bounds
from kpstudy.verify.graph import trace
from kpstudy.verify.profile import sampled_ranges
from tests.helpers.verify_nets import LocalNet, hull_vertices, mlp


def _case(kind: str, seed: int):
    if kind == "mlp":
        net = mlp(seed, sizes=(6, 8, 8, 3))
        return net, ConvexHull(hull_vertices(seed, 3, (6,), spread=1.0, dtype=torch.float64))
    return LocalNet(seed), ConvexHull(hull_vertices(seed, 3, (2, 11, 9), spread=0.5))


def _assert_contains_every_layer(net, hull, rules):
    """Every node's bounds under ``rules`` hold its sampled range."""
    graph = trace(net, hull.example_input())
    region = hull.region(hull.root(), graph.dtype)
    points = [hull.sample(300, 1), hull.sample(50, 2, "vertices"), hull.sample(100, 3, "edges")]
    low_s, high_s = sampled_ranges(graph, hull.image(torch.cat(points)).to(graph.dtype))
    checked = []

    def check(i, value):
        low, high = value.bounds()
        tol = 1e-5 * (1 + float(high_s[i].abs().max()))
        assert (low[0] <= low_s[i] + tol).all() and (high[0] >= high_s[i] - tol).all(), i
        checked.append(i)

    with relu_rules(rules(region) if callable(rules) else rules), torch.no_grad():
        bounds.propagate(graph, region, check, zonotope=True)
    assert len(checked) == len(graph.nodes) - 1


@pytest.mark.parametrize("kind", ["mlp", "local"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_deepz_at_any_slope_bounds_every_sampled_layer(kind, seed):
    net, hull = _case(kind, seed)
    seen = Recorded()
    _assert_contains_every_layer(net, hull, seen)
    assert seen.seen, "no ReLU was relaxed"
    g = torch.Generator().manual_seed(seed)
    slopes = {i: torch.rand(s.shape, generator=g, dtype=s.dtype) for i, s in seen.seen.items()}
    slopes[min(slopes)].view(-1)[:3] = torch.tensor([0.0, 1.0, 0.5])  # the ends included
    _assert_contains_every_layer(net, hull, Slopes(slopes))


@pytest.mark.parametrize("kind", ["mlp", "local"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_crown_tightened_preactivations_bound_every_layer_with_fewer_unstable_neurons(kind, seed):
    net, hull = _case(kind, seed)
    made = []

    def tightened(region):
        made.append(Tightened(region, rows=3))  # several chunks of rows
        return made[-1]

    _assert_contains_every_layer(net, hull, tightened)
    counts = list(made[0].counts.values())
    assert counts and all(after <= before for before, after in counts)


def test_node_at_follows_the_split_order_down_one_path():
    hull = ConvexHull(hull_vertices(0, 3, (4,)))
    nodes = hull.root()
    for _ in range(5):
        nodes = hull.split(nodes)
    for index in (0, 3, 17, 31):
        assert torch.equal(node_at(hull, 5, index).vertices, hull.image(nodes[index], hull.dtype))
