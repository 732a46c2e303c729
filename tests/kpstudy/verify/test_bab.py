"""Branch and bound: never 'holds' on a violated instance, counterexamples reproduce,
and the search decides small instances that the root bounds alone cannot."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.verify import ArgmaxSpec, ConvexHull, Parallelotope, verify
from tests.helpers.verify_nets import MixedNet, PoolProxy, hull_vertices

#: A node budget that decides every instance that must be decided here (the largest takes
#: about 300 nodes), so no verdict depends on the machine's speed; the timeout (s) only caps
#: a stalled run.
NODES, CAP = 1000, 600.0


def _spec_at_seed(net, x0, group_sizes):
    """Targets = the model's own argmax on the seed image, per group."""
    with torch.no_grad():
        y = net(x0[None]).flatten()
    targets, lo = [], 0
    for s in group_sizes:
        targets.append(int(y[lo : lo + s].argmax()))
        lo += s
    return ArgmaxSpec(group_sizes, targets)


def _sampled_violation(net, s, spec, seed):
    pts = torch.cat(
        [s.sample(1500, seed), s.sample(300, seed, "vertices"), s.sample(300, seed, "edges")]
    )
    with torch.no_grad():
        m = spec.group_min(spec.margins(net(s.image(pts)).flatten(1)))
    return bool((m <= 0).any())


def _check_counterexample(net, s, spec, result):
    c = result.counterexample
    assert c is not None and bool(s.contains_point(c.point))
    torch.testing.assert_close(c.image, s.image(c.point))
    with torch.no_grad():
        m = spec.group_min(spec.margins(net(c.image[None]).flatten(1)))
    assert m[0, c.group] <= 0 and result.group_status[c.group] == "violated"


def _check_margin_ends(net, s, spec, result):
    """The root's lower bound ≤ the smallest margin of the points tried ≤ the margin at
    the first vertex; 'holds' groups had no point at or below zero, a counterexample's
    group one at or below its margin."""
    with torch.no_grad():
        at_x0 = spec.group_min(spec.margins(net(s.image(s.root()[:, 0])).flatten(1)))[0]
    tried = torch.tensor(result.stats["attack_margin"], dtype=torch.float64)
    assert torch.all(tried <= at_x0.double() + 1e-6)  # float32 batches round differently
    root = result.stats["root_margin"]
    if root is not None:
        assert torch.all(torch.tensor(root, dtype=torch.float64) <= tried + 1e-6)
    for g, status in enumerate(result.group_status):
        if status == "holds":
            assert tried[g] > 0
    if result.counterexample is not None:
        assert tried[result.counterexample.group] <= result.counterexample.margin


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("set_type", [ConvexHull, Parallelotope])
@pytest.mark.parametrize("method", ["forward", "zonotope"])
def test_verify_is_sound_and_decides_mixed_nets(seed, set_type, method):
    net = MixedNet(seed)
    V = hull_vertices(seed, 1 + seed % 4, (2, 8, 8), spread=0.05 + 0.05 * (seed % 3))
    spec = _spec_at_seed(net, V[0], [3, 3])
    s = set_type(V)
    result = verify(net, s, spec, method=method, max_nodes=NODES, timeout=CAP)
    assert result.status in ("holds", "violated")  # complete on these small instances
    _check_margin_ends(net, s, spec, result)
    if result.status == "holds":
        assert not _sampled_violation(net, s, spec, seed)
        assert result.group_status == ["holds", "holds"]
    else:
        _check_counterexample(net, s, spec, result)


@pytest.mark.parametrize("seed", range(8))
def test_verify_proxy_with_excluded_group(seed):
    net = PoolProxy(seed)
    V = hull_vertices(seed, 3, (1, 10, 10), spread=0.1)
    full = _spec_at_seed(net, V[0], net.group_sizes)
    spec = ArgmaxSpec(net.group_sizes, [full.targets[0], None])
    result = verify(net, ConvexHull(V), spec, max_nodes=NODES, timeout=CAP)
    assert result.group_status[1] == "excluded"
    if result.status == "holds":
        assert not _sampled_violation(net, ConvexHull(V), spec, seed)
    else:
        assert result.status == "violated"
        _check_counterexample(net, ConvexHull(V), spec, result)


def test_branching_proves_what_the_root_cannot():
    """y0 = relu(x) beats y1 = relu(x) − 0.1 on x ∈ [−1, 1]. Intervals lose the correlation
    (the margin's interval bound is relu(a) − relu(b) + 0.1 on [a, b]) until nodes are
    narrower than 0.1; CROWN's backward pass and the zonotope's shared error symbol keep it
    and prove the root."""
    net = nn.Sequential(nn.Linear(1, 2), nn.ReLU(), nn.Linear(2, 2)).double().eval()
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0], [-1.0]]))
        net[0].bias.zero_()
        net[2].weight.copy_(torch.tensor([[1.0, 0.0], [1.0, 0.0]]))
        net[2].bias.copy_(torch.tensor([0.0, -0.1]))
    hull = ConvexHull(torch.tensor([[-1.0], [1.0]], dtype=torch.float64))
    spec = ArgmaxSpec([2], [0])
    root = verify(net, hull, spec, max_nodes=1, method="ibp", timeout=CAP)
    assert root.status == "unknown" and root.group_status == ["unknown"]
    result = verify(net, hull, spec, method="ibp", max_nodes=NODES, timeout=CAP)
    assert result.status == "holds" and result.nodes > 16
    assert verify(net, hull, spec, method="crown", max_nodes=1, timeout=CAP).status == "holds"
    # The zonotope's error symbol is shared by y0 and y1, so their margin is exact.
    assert verify(net, hull, spec, method="zonotope", max_nodes=1, timeout=CAP).status == "holds"


def test_violation_found_in_the_middle_of_the_hull():
    """Margins positive at every vertex and the centroid, negative on a small region found
    by the gradient attack or by splitting."""
    net = nn.Sequential(nn.Linear(1, 2), nn.ReLU(), nn.Linear(2, 2)).double().eval()
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0], [-1.0]]))
        net[0].bias.copy_(torch.tensor([-0.3, 0.3]))
        net[2].weight.copy_(torch.tensor([[1.0, 1.0], [0.0, 0.0]]))
        net[2].bias.copy_(torch.tensor([0.0, -0.05]))
    # y0 = |x - 0.3| beats y1 = -0.05... always: make it fail near x = 0.3 with y1 = +0.05
    with torch.no_grad():
        net[2].bias.copy_(torch.tensor([0.0, 0.05]))
    hull = ConvexHull(torch.tensor([[-1.0], [1.0]], dtype=torch.float64))
    result = verify(net, hull, ArgmaxSpec([2], [0]), max_nodes=NODES, timeout=CAP)
    assert result.status == "violated"
    _check_counterexample(net, hull, ArgmaxSpec([2], [0]), result)
    lam = result.counterexample.point
    assert abs(float(hull.image(lam)) - 0.3) < 0.05


def test_budget_gives_unknown_not_holds():
    net = MixedNet(0)
    V = hull_vertices(0, 4, (2, 8, 8), spread=3.0)
    spec = _spec_at_seed(net, V[0], [3, 3])
    result = verify(net, ConvexHull(V), spec, max_nodes=1, attack_steps=0, timeout=CAP)
    assert result.status in ("unknown", "violated")
    assert result.nodes <= 1
    _check_margin_ends(net, ConvexHull(V), spec, result)


def test_timeout_inside_a_node_leaves_it_open(monkeypatch):
    """A zonotope node on a large network can take minutes: the deadline is checked
    between layers, and the node stays open ('unknown', never 'holds')."""
    from kpstudy.verify import bounds

    net = MixedNet(3)
    V = hull_vertices(3, 2, (2, 8, 8), spread=0.05)
    spec = _spec_at_seed(net, V[0], [3, 3])
    ticks = iter(range(10**6))  # a clock that jumps 1 s per reading
    monkeypatch.setattr(bounds.time, "perf_counter", lambda: float(next(ticks)))
    result = verify(net, ConvexHull(V), spec, method="zonotope", timeout=5.0)
    assert result.status == "unknown" and result.stats["timed_out"]
    assert result.nodes == 0 and result.group_status == ["unknown", "unknown"]


def test_bad_input_is_named():
    net = MixedNet(0)
    V = hull_vertices(0, 2, (2, 8, 8))
    spec = ArgmaxSpec([3, 3], [0, 0])
    with pytest.raises(ValueError, match="vertices: expected .* at least two images"):
        ConvexHull(V[:1])
    bad = V.clone()
    bad[1, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="vertices: expected finite"):
        ConvexHull(bad)
    with pytest.raises(ValueError, match="input_set: images of shape"):
        verify(net, ConvexHull(hull_vertices(0, 2, (3, 8, 8))), spec)
    with pytest.raises(ValueError, match="spec: expected a model with 5 outputs"):
        verify(net, ConvexHull(V), ArgmaxSpec([3, 2], [0, 0]))
    with pytest.raises(ValueError, match="model: unsupported operation Tanh"):
        verify(nn.Sequential(nn.Flatten(), nn.Linear(128, 6), nn.Tanh()), ConvexHull(V), spec)
    with pytest.raises(ValueError, match="timeout: expected"):
        verify(net, ConvexHull(V), spec, timeout=0)
    with pytest.raises(ValueError, match="method: expected"):
        verify(net, ConvexHull(V), spec, method="milp")


def test_close_margins_are_proved_in_float64_and_ties_are_violations():
    net = nn.Sequential(nn.Linear(1, 2)).eval()
    hull = ConvexHull(torch.tensor([[-1.0], [1.0]]))
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1e-7], [0.0]]))
        net[0].bias.copy_(torch.tensor([2e-6, 0.0]))  # margin in [1.9e-6, 2.1e-6] < tol
    result = verify(net, hull, ArgmaxSpec([2], [0]), max_nodes=NODES, timeout=CAP)
    assert result.status == "holds" and result.stats["float64_rechecks"] >= 1
    with torch.no_grad():
        net[0].weight.zero_()
        net[0].bias.zero_()  # a tie everywhere
    result = verify(net, hull, ArgmaxSpec([2], [0]), max_nodes=NODES, timeout=CAP)
    assert result.status == "violated" and result.counterexample.margin == 0.0


@pytest.mark.parametrize("spread", [0.05, 0.3, 3.0])
def test_margin_bracket_contains_the_sampled_minimum(spread):
    """The worst keypoint's margin: root lower bound ≤ every sampled margin, and the
    attacks' smallest margin ≤ the margin at the seed; no lower end without a root bound."""
    net = MixedNet(3)
    V = hull_vertices(3, 3, (2, 8, 8), spread=spread)
    spec = _spec_at_seed(net, V[0], [3, 3])
    s = ConvexHull(V)
    result = verify(net, s, spec, max_nodes=1, method="zonotope", timeout=CAP)
    lower, upper = result.margin_bracket()
    with torch.no_grad():
        sampled = spec.group_min(spec.margins(net(s.image(s.sample(2000, 0))).flatten(1)))
        at_seed = spec.group_min(spec.margins(net(V[:1]).flatten(1)))
    assert upper is not None and upper <= float(at_seed.min()) + 1e-6
    if result.stats["root_margin"] is None:
        assert lower is None
    else:
        assert lower is not None and lower <= float(sampled.min()) + 1e-6


def test_a_counterexample_fails_at_the_exact_set_point_in_float64():
    """y0 − y1 = (x + b) − x with b = 1e-9 rounds to 0 in float32 for x ~ 1 (a tie, so a
    'violation' on every float32 image) but is +1e-9 at every exact hull point: no
    counterexample may be reported, the search goes on (float64 bounds prove it)."""
    net = nn.Sequential(nn.Linear(1, 2)).eval()
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0], [1.0]]))
        net[0].bias.copy_(torch.tensor([1e-9, 0.0]))
    hull = ConvexHull(torch.tensor([[1.0], [2.0]]))
    with torch.no_grad():
        y = net(hull.image(hull.sample(50, 0)))
    assert (y[:, 0] <= y[:, 1]).all()  # float32 sees a tie everywhere
    result = verify(net, hull, ArgmaxSpec([2], [0]), max_nodes=8, timeout=CAP)
    assert result.counterexample is None and result.status in ("holds", "unknown")
    assert result.stats["attack_margin"][0] > 0  # the float64 margins of the points tried


def test_verify_refuses_a_hull_of_another_dtype_than_the_model():
    from kpstudy.verify import ArgmaxSpec, ConvexHull, verify
    from tests.helpers.verify_nets import MixedNet, hull_vertices

    net = MixedNet(0).eval()  # float32
    hull = ConvexHull(hull_vertices(0, 3, (2, 8, 8), dtype=torch.float64))
    with pytest.raises(ValueError, match=r"input_set: expected images of the model's dtype"):
        verify(net, hull, ArgmaxSpec([3, 3], [0, 0]), timeout=5)
