"""Soundness of the bound methods: sampling, exact MILP optima, and relative tightness."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import Bounds, LinearConstraint, milp
from torch import nn

from kpstudy.verify import Box, ConvexHull, Parallelotope, output_bounds
from tests.helpers.verify_nets import (
    LocalNet,
    MixedNet,
    PatchNet,
    PoolProxy,
    TinyResNet,
    block_hull_vertices,
    hull_vertices,
    mlp,
)

METHODS = ("ibp", "forward", "crown", "zonotope")


def _sample_images(input_set, seed):
    pts = torch.cat([input_set.sample(1000, seed), input_set.sample(500, seed + 1, "vertices")])
    pts = torch.cat([pts, input_set.sample(500, seed + 2, "edges")])
    return input_set.image(pts)


@pytest.mark.parametrize("n", range(1, 7))
@pytest.mark.parametrize("set_type", [ConvexHull, Parallelotope])
def test_bounds_contain_2000_samples_mixed_net(n, set_type):
    net = MixedNet(seed=n)
    s = set_type(hull_vertices(n, n, (2, 8, 8)))
    with torch.no_grad():
        y = net(_sample_images(s, seed=n))
    assert len(y) == 2000
    for method in METHODS:
        lo, hi = output_bounds(net, s, method)
        slack = 1e-5 * (1 + y.abs().max())
        assert (y >= lo - slack).all(), method
        assert (y <= hi + slack).all(), method


def test_bounds_contain_samples_box_and_proxy():
    net = PoolProxy(seed=3)
    x0 = torch.randn(1, 10, 10)
    box = Box(x0 - 0.1, x0 + 0.1)
    hull = ConvexHull(hull_vertices(4, 3, (1, 10, 10)))
    for s in (box, hull):
        with torch.no_grad():
            y = net(_sample_images(s, seed=5) if s is hull else s.sample(2000, 5))
        for method in METHODS:
            lo, hi = output_bounds(net, s, method)
            assert (y >= lo - 1e-5).all() and (y <= hi + 1e-5).all(), method


@pytest.mark.parametrize("seed", range(3))
def test_bounds_contain_samples_of_block_hulls_on_a_residual_network(seed):
    """T-resnet in miniature: strided residual blocks and a transposed-convolution decoder
    over the hull of a seed image and four 3×3 block occlusions; the zonotope keeps each
    block's symbols in their windows through the shortcut's add."""
    net = TinyResNet(seed)
    hull = ConvexHull(block_hull_vertices(seed))
    with torch.no_grad():
        y = net(_sample_images(hull, seed=seed))
    for method in ("forward", "zonotope"):
        lo, hi = output_bounds(net, hull, method)
        slack = 1e-5 * (1 + y.abs().max())
        assert (y >= lo - slack).all() and (y <= hi + slack).all(), method
    assert (hi - lo).max() > 0  # the blocks do reach the heatmaps


@pytest.mark.parametrize("seed", range(3))
def test_undecided_max_pooling_windows_stay_out_of_the_radius(seed):
    """The zonotope passes an undecided max-pooling window as its chosen input plus one
    error symbol for the excess: where the stem's pooling of a block hull leaves windows
    undecided, no interval enters the radius (which the later layers' |W| would widen),
    and the bounds still contain the samples."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify.graph import trace

    net = TinyResNet(seed)
    hull = ConvexHull(block_hull_vertices(seed))
    graph = trace(net, hull.vertices[:1])
    region = hull.region(hull.root(), graph.dtype)
    pool = next(i for i, n in enumerate(graph.nodes) if i and n.op.kind == "maxpool")
    with torch.no_grad():
        out, saved = B.propagate(graph, region, zonotope=True)
        y = net(_sample_images(hull, seed=seed))
    assert not saved[pool][1].all()  # some window is undecided
    assert (out.rad == 0).all()
    lo, hi = out.bounds()
    slack = 1e-5 * (1 + y.abs().max())
    assert (y >= lo[0] - slack).all() and (y <= hi[0] + slack).all()


def _interval(net, lo, hi):
    """Plain numpy interval arithmetic: pre-activation bounds for the MILP's big-M."""
    out = []
    for layer in net:
        if isinstance(layer, nn.Linear):
            W, b = layer.weight.detach().numpy(), layer.bias.detach().numpy()
            c, r = (lo + hi) / 2, (hi - lo) / 2
            lo, hi = W @ c + b - np.abs(W) @ r, W @ c + b + np.abs(W) @ r
            out.append((lo.copy(), hi.copy()))
        else:
            lo, hi = np.maximum(lo, 0), np.maximum(hi, 0)
    return out


def _milp_extremes(net, vertices):
    """Exact min and max of every output of a ReLU MLP over the hull (scipy MILP)."""
    X = vertices.numpy()
    n = X.shape[0] - 1
    linears = [m for m in net if isinstance(m, nn.Linear)]
    pre = _interval(net, X.min(0) - 1.0, X.max(0) + 1.0)
    # Variables: λ (n), then per layer z (pre-activation), and for hidden layers a, δ.
    lb, ub, integ = [], [], []

    def add(lo, hi, k):
        start = len(lb)
        lb.extend(lo)
        ub.extend(hi)
        integ.extend([k] * len(lo))
        return np.arange(start, len(lb))

    lam = add([0.0] * n, [1.0] * n, 0)
    rows, lo_c, hi_c = [], [], []

    def constraint(coef: dict, lo, hi):
        rows.append(coef)
        lo_c.append(lo)
        hi_c.append(hi)

    # x = X0 + D λ enters the first layer directly.
    prev = None
    for li, layer in enumerate(linears):
        W, b = layer.weight.detach().numpy(), layer.bias.detach().numpy()
        zl, zu = pre[li]
        z = add(zl - 1e-6, zu + 1e-6, 0)
        for j in range(W.shape[0]):
            coef = {z[j]: 1.0}
            if prev is None:
                const = W[j] @ X[0] + b[j]
                for i in range(n):
                    coef[lam[i]] = -(W[j] @ (X[i + 1] - X[0]))
            else:
                const = b[j]
                for k in range(W.shape[1]):
                    coef[prev[k]] = coef.get(prev[k], 0.0) - W[j, k]
            constraint(coef, const, const)
        if li == len(linears) - 1:
            out = z
            break
        a = add([0.0] * len(z), np.maximum(zu, 0) + 1e-6, 0)
        dl = add([0.0] * len(z), [1.0] * len(z), 1)
        for j in range(len(z)):
            constraint({a[j]: 1.0, z[j]: -1.0}, 0.0, np.inf)  # a ≥ z
            constraint({a[j]: 1.0, z[j]: -1.0, dl[j]: -zl[j]}, -np.inf, -zl[j])  # a ≤ z − l(1−δ)
            constraint({a[j]: 1.0, dl[j]: -max(zu[j], 0.0)}, -np.inf, 0.0)  # a ≤ u δ
        prev = a
    nv = len(lb)
    A = np.zeros((len(rows), nv))
    for r, coef in enumerate(rows):
        for k, v in coef.items():
            A[r, k] += v
    cons = [
        LinearConstraint(A, lo_c, hi_c),
        LinearConstraint(np.r_[np.ones(n), np.zeros(nv - n)], -np.inf, 1.0),
    ]
    mins, maxs = [], []
    for j in out:
        c = np.zeros(nv)
        c[j] = 1.0
        for sign, store in ((1.0, mins), (-1.0, maxs)):
            res = milp(sign * c, constraints=cons, integrality=integ, bounds=Bounds(lb, ub))
            assert res.success
            store.append(sign * res.fun)
    return np.array(mins), np.array(maxs)


@pytest.mark.parametrize("seed", range(6))
def test_bounds_enclose_exact_milp_extremes(seed):
    net = mlp(seed)
    n = 1 + seed % 4
    V = hull_vertices(seed, n, (6,), spread=0.5, dtype=torch.float64)
    lo_exact, hi_exact = _milp_extremes(net, V)
    hull = ConvexHull(V)
    # the exact extremes are attained: sampling gets close to them from inside
    with torch.no_grad():
        y = net(hull.image(hull.sample(4000, seed))).numpy()
    assert (y.min(0) >= lo_exact - 1e-7).all() and (y.max(0) <= hi_exact + 1e-7).all()
    for method in METHODS:
        lo, hi = (b.numpy() for b in output_bounds(net, hull, method))
        assert (lo <= lo_exact + 1e-9).all(), method
        assert (hi >= hi_exact - 1e-9).all(), method


def test_simplex_never_looser_than_parallelotope_and_tighter_on_average():
    ratios = []
    for seed in range(8):
        net = MixedNet(seed)
        V = hull_vertices(seed, 3, (2, 8, 8))
        for method in ("forward", "crown"):
            lo_h, hi_h = output_bounds(net, ConvexHull(V), method)
            lo_p, hi_p = output_bounds(net, Parallelotope(V), method)
            assert (lo_h >= lo_p - 1e-5).all() and (hi_h <= hi_p + 1e-5).all()
            ratios.append(((hi_h - lo_h).mean() / (hi_p - lo_p).mean()).item())
    assert np.mean(ratios) < 0.9


def test_crown_no_wider_than_ibp_and_forward_on_average():
    widths = {m: [] for m in METHODS}
    for seed in range(8):
        net = MixedNet(seed)
        hull = ConvexHull(hull_vertices(seed, 2, (2, 8, 8)))
        for m in METHODS:
            lo, hi = output_bounds(net, hull, m)
            widths[m].append((hi - lo).mean().item())
    assert np.mean(widths["crown"]) <= np.mean(widths["forward"]) <= np.mean(widths["ibp"])


def test_zonotope_stays_tight_where_forward_bounds_blow_up():
    """A deep narrow ReLU network and a small hull (the trained CNN's situation): forward
    radii grow as |W| per layer, the zonotope's shared error symbols keep their signs."""
    net = mlp(3, sizes=(8,) + (24,) * 10 + (4,))
    V = hull_vertices(3, 2, (8,), spread=0.02, dtype=torch.float64)
    hull = ConvexHull(V)
    with torch.no_grad():
        y = net(hull.image(hull.sample(2000, 0)))
    width = {}
    for method in ("forward", "zonotope"):
        lo, hi = output_bounds(net, hull, method)
        assert (y >= lo - 1e-9).all() and (y <= hi + 1e-9).all()
        width[method] = (hi - lo).mean().item()
    assert width["zonotope"] < 0.5 * width["forward"]


def test_zonotope_past_its_symbol_budget_stays_sound_and_loosens():
    from kpstudy.verify import bounds as B
    from kpstudy.verify.graph import trace

    def widths(net, hull, y):
        graph = trace(net, hull.vertices[:1])
        region = hull.region(hull.root(), graph.dtype)
        q, out = region.mid.shape[1], []
        for budget in (0, 5, None):
            stacks, _ = B.propagate(graph, region, zonotope=True, max_generators=budget)
            assert budget is None or stacks.mid.shape[1] - q <= budget
            lo, hi = stacks.bounds()
            slack = 1e-5 * (1 + y.abs().max())
            assert (y >= lo[0] - slack).all() and (y <= hi[0] + slack).all(), budget
            out.append((hi - lo).mean().item())
        return out

    with torch.no_grad():
        hull = ConvexHull(hull_vertices(4, 3, (2, 8, 8), spread=0.3))
        widths(MixedNet(seed=4), hull, MixedNet(seed=4)(_sample_images(hull, seed=4)))
        net = mlp(5, sizes=(8,) + (24,) * 6 + (4,))
        hull = ConvexHull(hull_vertices(5, 2, (8,), spread=0.5, dtype=torch.float64))
        none, few, full = widths(net, hull, net(_sample_images(hull, seed=5)))
    # Symbols a relaxation error cannot share are boxed: every budget is sound, fewer
    # symbols are looser (asserted on a ReLU network: which inputs a max pooling picks
    # depends on the bounds, so there the widths need not be ordered).
    assert none >= few >= full and none > 1.5 * full


@pytest.mark.parametrize("seed", range(2))
def test_a_symbols_footprint_bounds_its_windows_and_the_budget_counts_it(seed, monkeypatch):
    """Every window a symbol holds in any value (as the pass maps it through strided
    convolutions, a max pooling, a residual add and a transposed-convolution decoder) is
    within its maker's footprint (a ReLU's or the max pooling's), and a smaller element
    budget makes fewer symbols, within it, and looser bounds that still contain the
    samples."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify import operators, symbols
    from kpstudy.verify.graph import trace

    net = TinyResNet(seed)
    hull = ConvexHull(block_hull_vertices(seed))
    graph = trace(net, hull.vertices[:1])
    region = hull.region(hull.root(), graph.dtype)
    footprints = B.symbol_footprints(graph)
    assert footprints and all(0 < f <= 32 * 16 * 16 for f in footprints.values())
    makers, held = {}, []  # first symbol → its node; every block any operator returns
    make, pool = operators.ReLURules._blocks, operators.MaxPoolRules.zonotope

    def record_maker(self, p, i, x):
        makers[p.made] = i
        return make(self, p, i, x)

    def record_pool(self, p, i, ins):
        makers[p.made] = i
        return pool(self, p, i, ins)

    for name in ("apply", "combine"):
        real = getattr(symbols, name)

        def record(*args, real=real):
            out = real(*args)
            held.extend(out)
            return out

        monkeypatch.setattr(symbols, name, record)
    monkeypatch.setattr(operators.ReLURules, "_blocks", record_maker)
    monkeypatch.setattr(operators.MaxPoolRules, "zonotope", record_pool)
    y = net(_sample_images(hull, seed=seed)).detach()
    widths, made = [], []
    affine = region.mid.shape[1] * max(math.prod(n.shape) for n in graph.nodes)
    with torch.no_grad():
        for elements in (None, affine + 3000):
            if elements is not None:
                monkeypatch.setattr(B, "ZONOTOPE_ELEMENTS", elements)
            makers.clear()
            held.clear()
            out, _ = B.propagate(graph, region, zonotope=True)
            starts = sorted(makers)
            for b in held:
                maker = makers[max(s for s in starts if s <= b.start)]
                assert b.coeff[0, 0].numel() <= footprints[maker]
            ends = [*starts[1:], out.mid.shape[1]]
            kinds = [graph.nodes[makers[s]].op.kind for s in starts]
            assert elements is not None or any(  # undecided windows made symbols too
                k == "maxpool" and e > s for k, s, e in zip(kinds, starts, ends)
            )
            cost = sum((e - s) * footprints[makers[s]] for s, e in zip(starts, ends))
            assert elements is None or 0 < cost <= elements - affine
            lo, hi = out.bounds()
            slack = 1e-5 * (1 + y.abs().max())
            assert (y >= lo[0] - slack).all() and (y <= hi[0] + slack).all()
            widths.append((hi - lo).mean().item())
            made.append(out.mid.shape[1] - region.mid.shape[1])
    assert made[1] < made[0] and widths[1] > widths[0]


class _TwoReluBranches(nn.Module):
    """``y0 = relu(x) − relu(0.5 − x)`` (two parallel ReLU branches) and ``y1`` the affine
    part of y0's zonotope: if both branches numbered their new symbol alike, the margin
    ``y1 − y0`` would look like ``±0.0625·ε`` where it reaches −0.4375 (at x = 0.5)."""

    def __init__(self):
        super().__init__()
        self.a, self.b, self.c, self.d = (
            nn.Linear(1, 2),
            nn.Linear(1, 2),
            nn.Linear(2, 2),
            nn.Linear(1, 2),
        )
        with torch.no_grad():
            for layer, w, b in (
                (self.a, [[1.0], [0.0]], [0.0, 0.0]),
                (self.b, [[0.0], [-1.0]], [0.0, 0.5]),
                (self.c, [[1.0, -1.0], [0.0, 0.0]], [0.0, 0.0]),
                (self.d, [[0.0], [1.25]], [0.0, -0.5625]),
            ):
                layer.weight.copy_(torch.tensor(w))
                layer.bias.copy_(torch.tensor(b))

    def forward(self, x):
        return self.c(torch.relu(self.a(x)) + torch.relu(self.b(x))) + self.d(x)


def test_symbols_of_parallel_branches_stay_distinct():
    from kpstudy.verify import bounds as B
    from kpstudy.verify.graph import trace

    net = _TwoReluBranches().eval()
    hull = ConvexHull(torch.tensor([[-1.0], [1.0]]))
    graph = trace(net, hull.vertices[:1])
    region = hull.region(hull.root(), graph.dtype)
    with torch.no_grad():
        y = net(torch.linspace(-1, 1, 201)[:, None])
        true_min = (y[:, 1] - y[:, 0]).min()
        for method in ("forward", "zonotope"):
            lower = B.row_bounds(graph, region, torch.tensor([1]), torch.tensor([0]), method)
            assert lower.item() <= true_min + 1e-6, method


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("net_name", ["local", "pool", "resnet"])
def test_zonotope_symbol_blocks_equal_dense_stacks(net_name, seed, monkeypatch):
    """Error symbols kept in spatial blocks (kpstudy.verify.symbols) give the bounds of
    the dense stacks, for a batch of regions, through every block operator in awkward
    geometry (LocalNet), through the proxy's cell pools read block by block (PoolProxy;
    the last case has one-pixel cells, which pass unpooled) and through a strided max
    pooling before residual blocks (TinyResNet); and they contain 2000 sampled images."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify import symbols
    from kpstudy.verify.graph import trace

    if net_name == "local":
        net, shape = LocalNet(seed).double(), (2, 11, 9)
    elif net_name == "resnet":
        net, shape = TinyResNet(seed).double(), (3, 16, 16)
    else:
        dvs = [((1, 1), (1, 2)), ((2, 0), (0, 1)), ((1, 2), (2, 2)), ((0, 1), (3, 1))]
        dvs = (dvs + [((0, 0), (0, 0))])[seed]
        net, shape = PoolProxy(seed, dvs=dvs).double(), (1, 10, 10)
    hull = ConvexHull(hull_vertices(seed, 3, shape, spread=0.3, dtype=torch.float64))
    graph = trace(net, hull.vertices[:1])
    nodes = hull.split(hull.split(hull.root()))  # four regions in one batch
    region = hull.region(nodes, graph.dtype)
    with torch.no_grad():
        y = net(_sample_images(hull, seed))
        blocks, _ = B.propagate(graph, region, zonotope=True)
        monkeypatch.setattr(symbols, "is_local", lambda *args: False)
        dense, _ = B.propagate(graph, region, zonotope=True)
    # The same symbols (blocks number them per ReLU, padded to the batch): every linear
    # function of the output has the same bounds, margins included.
    q, outputs = region.mid.shape[1], y[0].numel()
    g = torch.Generator().manual_seed(seed)
    eye = torch.eye(outputs, dtype=torch.float64)
    A = torch.cat([torch.randn(8, outputs, dtype=torch.float64, generator=g), eye, -eye])
    lows = []
    for out in (blocks, dense):
        coeff = out.mid.flatten(2) @ A.T
        coeff[:, :q] -= out.rad.flatten(2) @ A.abs().T
        lows.append(B.zonotope_min(coeff, q, "simplex"))
    torch.testing.assert_close(lows[0], lows[1])
    torch.testing.assert_close(blocks.rad, dense.rad)
    lo, hi = blocks.bounds()
    assert (y >= lo.min(0).values - 1e-9).all() and (y <= hi.max(0).values + 1e-9).all()


@pytest.mark.parametrize("net_name", ["local", "pool"])
def test_zonotope_bounds_have_the_gradient_of_their_finite_differences(net_name):
    """The symbol blocks' backward (kpstudy.verify.symbols) is the derivative of
    the bounds in the network's parameters: directional finite differences, float64."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify.graph import trace

    if net_name == "local":
        net, shape = LocalNet(1).double(), (2, 11, 9)
    else:
        net, shape = PoolProxy(1, dvs=((1, 1), (1, 2))).double(), (1, 10, 10)
    hull = ConvexHull(hull_vertices(1, 3, shape, spread=0.3, dtype=torch.float64))
    graph = trace(net, hull.vertices[:1], differentiable=True)
    region = hull.region(hull.split(hull.root()), graph.dtype)

    def width():
        out, _ = B.propagate(graph, region, zonotope=True)
        assert out.mid.shape[1] > out.rad.shape[1]  # error symbols were made
        low, high = out.bounds()
        return (high - low).sum() + low.sum()

    params = list(net.parameters())
    width().backward()
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        v = [torch.randn(p.shape, dtype=p.dtype, generator=g) for p in params]
        slope = sum((p.grad * d).sum() for p, d in zip(params, v))
        values = []
        with torch.no_grad():
            for h in (1e-6, -2e-6):
                for p, d in zip(params, v):
                    p += h * d
                values.append(width())
            for p, d in zip(params, v):
                p += 1e-6 * d
        torch.testing.assert_close((values[0] - values[1]) / 2e-6, slope, rtol=1e-4, atol=1e-6)


def test_bounds_are_exact_on_a_linear_network():
    net = nn.Sequential(nn.Conv2d(2, 3, 3), nn.Flatten(), nn.Linear(3 * 6 * 6, 4)).double().eval()
    V = hull_vertices(0, 3, (2, 8, 8), dtype=torch.float64)
    with torch.no_grad():
        y = net(V)  # a linear map's extremes over a hull are at its vertices
    for method in ("forward", "crown", "zonotope"):
        lo, hi = output_bounds(net, ConvexHull(V), method)
        torch.testing.assert_close(lo, y.min(0).values)
        torch.testing.assert_close(hi, y.max(0).values)


@pytest.mark.parametrize("seed", range(3))
def test_a_patch_decoder_is_fused_into_one_exact_map_no_looser(seed, monkeypatch):
    """Transposed convolutions whose kernels equal their strides (batch norms between)
    trace to one PatchConvTranspose: the same map in float64, and zonotope bounds that
    contain 2000 samples and are nowhere wider than the unfused layers' (whose radius
    goes through each layer's |W|)."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify import graph as G
    from kpstudy.verify.ops import PatchConvTranspose

    net = PatchNet(seed).double()
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5, dtype=torch.float64))
    graph = G.trace(net, hull.vertices[:1])
    assert isinstance(graph.nodes[-1].op, PatchConvTranspose)
    assert sum(isinstance(n.op, G.ops.ConvTranspose) for n in graph.nodes) == 1
    with torch.no_grad():
        x = _sample_images(hull, seed)
        y = net(x)
        torch.testing.assert_close(graph.forward(x), y, rtol=1e-12, atol=1e-12)
        region = hull.region(hull.root(), graph.dtype)
        # A budget of a few symbols: the rest go to the radius, which the fused map keeps tight.
        lo, hi = B.propagate(graph, region, zonotope=True, max_generators=4)[0].bounds()
        monkeypatch.setattr(G, "_fuse_patch_chains", lambda nodes: nodes)
        apart = G.trace(net, hull.vertices[:1])
        assert sum(isinstance(n.op, G.ops.ConvTranspose) for n in apart.nodes) == 3
        lo3, hi3 = B.propagate(apart, region, zonotope=True, max_generators=4)[0].bounds()
    assert (y >= lo - 1e-9).all() and (y <= hi + 1e-9).all()
    assert (hi - lo <= hi3 - lo3 + 1e-9).all() and ((hi - lo) < (hi3 - lo3) - 1e-6).any()


@pytest.mark.parametrize("offsets", [64, 0])
@pytest.mark.parametrize("seed", range(3))
def test_an_output_kept_in_blocks_reads_as_the_dense_stack(seed, offsets, monkeypatch):
    """propagate(dense=False): the output's symbol reach and its symbols on chosen entries
    (Region.reach, Region.symbols_at; entries repeated and on several channels) are the
    dense stack's, whether the reach adds the windows offset by offset or entry by entry
    (symbols.REACH_OFFSETS)."""
    from kpstudy.verify import bounds as B
    from kpstudy.verify import symbols
    from kpstudy.verify.graph import trace

    monkeypatch.setattr(symbols, "REACH_OFFSETS", offsets)

    net = PatchNet(seed).double()
    hull = ConvexHull(hull_vertices(seed, 3, (2, 8, 8), spread=0.5, dtype=torch.float64))
    graph = trace(net, hull.vertices[:1])
    region = hull.region(hull.split(hull.split(hull.root())), graph.dtype)
    with torch.no_grad():
        kept, _ = B.propagate(graph, region, zonotope=True, dense=False)
        dense, _ = B.propagate(graph, region, zonotope=True)
    assert kept.blocks and kept.mid.shape[1] == kept.rad.shape[1]
    q = kept.rad.shape[1]
    torch.testing.assert_close(kept.reach(), dense.reach())
    index = torch.randperm(3 * 16 * 16, generator=torch.Generator().manual_seed(seed))[:50]
    index = torch.cat([index, index[:7]])
    torch.testing.assert_close(kept.symbols_at(index), dense.mid[:, q:].flatten(2)[..., index])
    torch.testing.assert_close(kept.symbols_at(index), dense.symbols_at(index))
    for a, b in zip(kept.bounds(), dense.bounds()):
        torch.testing.assert_close(a, b)


def test_unknown_method_is_refused():
    net = mlp(0)
    with pytest.raises(ValueError, match="method: expected"):
        output_bounds(net, ConvexHull(torch.randn(2, 6).double()), "deeppoly")


def test_a_smoothed_patch_decoder_traces_to_one_filtered_patch_map():
    """HeatmapCNNPatchSmoothDecoder (the shipped verification-friendly CNN's backbone):
    its four transposed convolutions and its per-keypoint 3×3 filter fuse into one
    transposed convolution with overlapping 6×6 patches whose linear map is the pair's,
    the traced graph is the network in float64, and the zonotope's bounds contain 200
    sampled heatmaps and the vertices'."""
    from kpstudy.models.cnn import HeatmapCNNPatchSmoothDecoder
    from kpstudy.verify import bounds as B
    from kpstudy.verify.graph import trace
    from kpstudy.verify.ops import FilteredPatchConvTranspose, PatchConvTranspose

    torch.manual_seed(0)
    net = HeatmapCNNPatchSmoothDecoder(3)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
        net[-1].weight.uniform_(-0.5, 1.0)
    net = net.double().eval()
    hull = ConvexHull(hull_vertices(0, 3, (3, 64, 64), spread=0.02, dtype=torch.float64) + 0.5)
    graph = trace(net, hull.vertices[:1])
    kinds = [type(n.op) for n in graph.nodes]
    assert kinds[-1] is FilteredPatchConvTranspose and kinds.count(kinds[-1]) == 1
    fused = graph.nodes[-1].op
    assert type(fused.patch) is PatchConvTranspose and fused.m.kernel_size == (6, 6)
    region = hull.region(hull.root(), graph.dtype)
    with torch.no_grad():
        z = torch.randn(5, *graph.nodes[-2].shape, dtype=torch.float64)
        pair = fused.filter.linear(fused.patch.linear(z))
        torch.testing.assert_close(fused.linear(z), pair, rtol=1e-12, atol=1e-12)
        abs_pair = fused.filter.abs_linear(fused.patch.abs_linear(z.abs()))
        assert (fused.abs_linear(z.abs()) <= abs_pair + 1e-12).all()
        x = torch.cat([hull.image(hull.sample(200, 0)), hull.vertices])
        y = net(x)
        torch.testing.assert_close(graph.forward(x), y, rtol=1e-12, atol=1e-12)
        lo, hi = B.propagate(graph, region, zonotope=True)[0].bounds()
    assert (y >= lo - 1e-9).all() and (y <= hi + 1e-9).all()
    assert ((hi - lo) > 1e-6).any()


@pytest.mark.parametrize("smooth", [False, True])
def test_an_affine_tail_split_off_carries_the_heads_symbols_exactly(smooth):
    """``Graph.split_affine_tail`` cuts a patch decoder's graph after its last ReLU: the
    head's zonotope (symbols in blocks) through the tail is the whole pass's output in
    float64; the tail narrowed to some output channels gives those channels; and the
    tail on the head's symbols moved into the radius contains the exact bounds."""
    from kpstudy.models.cnn import HeatmapCNNPatchSmoothDecoder
    from kpstudy.verify import bounds as B
    from kpstudy.verify import symbols
    from kpstudy.verify.graph import trace

    if smooth:
        torch.manual_seed(1)
        net, shape, spread = HeatmapCNNPatchSmoothDecoder(3).double().eval(), (3, 64, 64), 0.02
    else:
        net, shape, spread = PatchNet(1).double(), (2, 8, 8), 0.5
    hull = ConvexHull(hull_vertices(1, 3, shape, spread=spread, dtype=torch.float64) + 0.5)
    graph = trace(net, hull.vertices[:1])
    head, tail = graph.split_affine_tail()
    assert head.nodes[-1].op.kind == "relu" and len(tail.nodes) == 2
    assert trace(nn.Sequential(net, nn.ReLU()), hull.vertices[:1]).split_affine_tail() is None
    nodes = hull.split(hull.split(hull.root()))
    region = hull.region(nodes, graph.dtype)
    with torch.no_grad():
        whole = B.propagate(graph, region, zonotope=True, dense=False)[0]
        inner = B.propagate(head, region, zonotope=True, dense=False)[0]
        out = B.propagate(tail, inner, zonotope=True, dense=False)[0]
        dense = symbols.dense(out.mid, out.blocks, out.rows)
        torch.testing.assert_close(dense, symbols.dense(whole.mid, whole.blocks, whole.rows))
        torch.testing.assert_close(out.rad, whole.rad)
        channels = torch.tensor([2, 0])
        narrow = tail.output_channels(channels)
        some = inner.select(torch.tensor([1, 3]))
        part = B.propagate(narrow, some, zonotope=True, dense=False)[0]
        lo, hi = part.bounds()
        want_lo, want_hi = (b[[1, 3]][:, channels] for b in out.bounds())
        torch.testing.assert_close(lo, want_lo)
        torch.testing.assert_close(hi, want_hi)
        x = torch.randn(4, *tail.nodes[0].shape, dtype=torch.float64)
        torch.testing.assert_close(narrow.forward(x), tail.forward(x)[:, channels])
        loose_lo, loose_hi = B.propagate(tail, inner.without_symbols())[0].bounds()
        exact_lo, exact_hi = out.bounds()
    assert (loose_lo <= exact_lo + 1e-12).all() and (loose_hi >= exact_hi - 1e-12).all()
    assert ((exact_lo - loose_lo) > 1e-6).any()  # the symbols' signs were worth keeping
