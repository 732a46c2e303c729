"""The operator registry: the documented "adding a layer" examples run through every
method, unknown kinds refused, and the cell pool traced as one function."""

from __future__ import annotations

import ast
import re
import textwrap
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from kpstudy.verify import Box, ConvexHull, Parallelotope, graph, operators, ops, output_bounds
from kpstudy.verify.graph import trace
from tests.helpers.verify_nets import PoolProxy, hull_vertices

METHODS = ("ibp", "forward", "crown", "zonotope")


@pytest.fixture
def leaky(monkeypatch):
    """Run the module docstring's examples on copies of the two registries."""
    monkeypatch.setattr(operators, "RULES", dict(operators.RULES))
    monkeypatch.setattr(graph, "MODULES", dict(graph.MODULES))
    block = re.search(r"::\n\n(.*?)\n\n``tests/", operators.__doc__, re.S).group(1)
    names = {"ops": ops, "Rules": operators.Rules, "RULES": operators.RULES, "graph": graph}
    names |= {"Region": operators.Region, "torch": torch, "nn": nn, "F": F}
    exec(textwrap.dedent(block), names)
    return names


class _LeakyNet(nn.Module):
    def __init__(self, seed: int, c: float):
        super().__init__()
        torch.manual_seed(seed)
        self.conv1 = nn.Conv2d(2, 4, 3, padding=1)
        self.conv2 = nn.Conv2d(4, 4, 3, padding=1)
        self.leaky = nn.LeakyReLU(c)
        self.pool = nn.MaxPool2d(2)
        self.fc = nn.Linear(4 * 4 * 4, 5)
        self.eval()

    def forward(self, x):
        h = self.leaky(self.conv1(x))
        h = self.pool(torch.relu(self.conv2(h)))
        return self.fc(self.leaky(h).flatten(1))


def _every_method_bounds_the_samples(net, V):
    """Over the hull of ``V``, its parallelotope and its box."""
    for s in (ConvexHull(V), Parallelotope(V), Box(V.min(0).values, V.max(0).values)):
        pts = s.sample(1000, 0) if isinstance(s, Box) else s.image(s.sample(1000, 0))
        with torch.no_grad():
            y = net(pts)
        for method in METHODS:
            lo, hi = output_bounds(net, s, method)
            slack = 1e-5 * (1 + y.abs().max())
            assert (y >= lo - slack).all() and (y <= hi + slack).all(), (type(s), method)


@pytest.mark.parametrize("c", [0.0, 0.1, 0.7])
def test_the_documented_leaky_relu_bounds_its_samples_with_every_method(leaky, c):
    net = _LeakyNet(seed=int(10 * c), c=c)
    V = hull_vertices(1, 3, (2, 8, 8), spread=0.3)
    nodes = trace(net, V[:1]).nodes
    assert [type(n.op).__name__ for n in nodes].count("LeakyReLU") == 2
    _every_method_bounds_the_samples(net, V)


@pytest.mark.parametrize("c", [0.0, 0.1, 0.7])
def test_the_documented_leaky_relu_is_tight_where_its_relaxation_is(leaky, c):
    """One layer, float64: the chord touches the function at the pre-activation's ends,
    which vertices of the set reach, so a wrong offset or slope shows on the samples."""
    torch.manual_seed(3)
    net = nn.Sequential(nn.Linear(4, 16), nn.LeakyReLU(c)).double().eval()
    V = hull_vertices(3, 3, (4,), spread=1.0, dtype=torch.float64)
    for s in (ConvexHull(V), Parallelotope(V)):
        kinds = ("dirichlet", "vertices", "edges")
        pts = torch.cat([s.image(s.sample(300, k, kind)) for k, kind in enumerate(kinds)])
        with torch.no_grad():
            y = net(pts)
        for method in METHODS:
            lo, hi = output_bounds(net, s, method)
            assert (y >= lo - 1e-9).all() and (y <= hi + 1e-9).all(), (type(s), method)
            if method != "ibp":  # the upper bounds are reached (on vertices)
                assert ((hi - y.max(0).values).abs() < 1e-9).float().mean() > 0.5, method


def test_a_leaky_relu_of_slope_zero_is_bounded_as_a_relu_is(leaky):
    """With ``c = 0`` the example's rule is the ReLU's interval arithmetic."""
    V = hull_vertices(2, 3, (2, 8, 8), spread=0.3)
    box = Box(V.min(0).values, V.max(0).values)
    leaky_net, relu_net = _LeakyNet(seed=0, c=0.0), _LeakyNet(seed=0, c=0.0)
    relu_net.leaky = nn.ReLU()
    for a, b in zip(output_bounds(leaky_net, box, "ibp"), output_bounds(relu_net, box, "ibp")):
        torch.testing.assert_close(a, b)


class _UpsampleNet(nn.Module):
    def __init__(self, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        self.conv1 = nn.Conv2d(2, 3, 3, padding=1)
        self.up = nn.Upsample(scale_factor=2)
        self.conv2 = nn.Conv2d(3, 2, 3, stride=2, padding=1)
        self.fc = nn.Linear(2 * 6 * 5, 4)
        self.eval()

    def forward(self, x):
        h = self.up(torch.relu(self.conv1(x)))
        return self.fc(torch.relu(self.conv2(h)).flatten(1))


@pytest.mark.parametrize("seed", range(3))
def test_the_documented_upsampling_keeps_symbol_blocks_and_bounds_its_samples(
    leaky, seed, monkeypatch
):
    """The affine example maps error-symbol windows itself: the zonotope with its blocks
    has the dense stacks' bounds, and every method contains the samples."""
    net = _UpsampleNet(seed)
    V = hull_vertices(seed, 3, (2, 6, 5), spread=0.3)
    up, calls = leaky["Upsample2"], []
    original = up.map_window

    def counted(self, *args):
        calls.append(args)
        return original(self, *args)

    monkeypatch.setattr(up, "map_window", counted)
    _every_method_bounds_the_samples(net, V)
    assert calls  # the zonotope kept its symbols in blocks through the upsampling
    hull = ConvexHull(V.double())
    blocks = output_bounds(net.double(), hull, "zonotope")
    monkeypatch.setattr(up, "local", False)
    dense = output_bounds(net, hull, "zonotope")
    for a, b in zip(blocks, dense):
        torch.testing.assert_close(a, b)


def test_an_unknown_kind_is_refused_in_one_line_naming_it(monkeypatch):
    class Odd(ops.Op):
        kind = "odd"

        def forward(self, x):
            return x.abs()

    monkeypatch.setitem(graph.MODULES, nn.Tanh, lambda m: Odd())
    net = nn.Sequential(nn.Linear(3, 3), nn.Tanh(), nn.Linear(3, 2)).eval()
    with pytest.raises(
        ValueError, match=r"^model: operator kind 'odd' has no bound rules \(node"
    ) as e:
        trace(net, torch.zeros(1, 3))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"^operator kind 'odd' has no bound rules") as e:
        operators.rules("odd")
    assert "\n" not in str(e.value)


def test_the_cell_pool_is_traced_as_one_function_node():
    net = PoolProxy(3).double()
    x = torch.randn(4, 1, 10, 10, dtype=torch.float64)
    g = trace(net, x[:1])
    pools = [n for n in g.nodes[1:] if isinstance(n.op, ops.CellPool)]
    assert len(pools) == 2 and all(n.op.kind == "affine" for n in pools)
    assert (pools[0].op.n_v, pools[0].op.n_h) == (net.pools[0].n_v, net.pools[0].n_h)
    with torch.no_grad():
        assert torch.equal(g.forward(x), net(x))


def test_the_verifier_does_not_import_the_pooling_layer():
    """kpstudy.models.pooling uses the verifier's functional cell pool, not the other way round."""
    for path in Path(operators.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert node.module != "kpstudy.models.pooling", path.name
            elif isinstance(node, ast.Import):
                assert all(a.name != "kpstudy.models.pooling" for a in node.names), path.name
