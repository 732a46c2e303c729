"""ONNX + VNN-LIB export of a verification instance (kpstudy.verify.export)."""

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from torch import nn

from kpstudy.pooling import build_cell_pool
from kpstudy.verify.export import export_instance, read_vnnlib_polytope
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.spec import ArgmaxSpec

S = (3, 8, 8)


def conv_net(seed=0):
    """Conv → BatchNorm (random running stats) → ReLU → AvgPool → Linear: 6 outputs."""
    torch.manual_seed(seed)
    bn = nn.BatchNorm2d(4)
    bn.running_mean.uniform_(-0.5, 0.5)
    bn.running_var.uniform_(0.5, 2.0)
    nn.init.uniform_(bn.weight, 0.5, 1.5)
    nn.init.uniform_(bn.bias, -0.5, 0.5)
    net = nn.Sequential(
        nn.Conv2d(3, 4, 3, padding=1),
        bn,
        nn.ReLU(),
        nn.AvgPool2d(2),
        nn.Flatten(),
        nn.Linear(64, 6),
    )
    return net.eval()


class TwoKeypointNet(nn.Module):
    """Conv to two heatmap channels, each pooled into its keypoint's cells, concatenated."""

    def __init__(self, seed=0):
        super().__init__()
        torch.manual_seed(seed)
        self.conv = nn.Conv2d(3, 2, 3, padding=1)
        self.pool_a, self.target_a = build_cell_pool((2, 5), (1, 2), S[1:])
        self.pool_b, self.target_b = build_cell_pool((7, 0), (0, 1), S[1:])

    def forward(self, x):
        h = self.conv(x)
        a, b = self.pool_a(h[:, :1]), self.pool_b(h[:, 1:])
        return torch.cat([a.flatten(1), b.flatten(1)], 1)

    def spec(self, keep_b=True):
        sizes = [p.n_v * p.n_h for p in (self.pool_a, self.pool_b)]
        return ArgmaxSpec(sizes, [self.target_a, self.target_b if keep_b else None])


def hull(n, seed=0, cls=ConvexHull):
    g = torch.Generator().manual_seed(seed)
    return cls(torch.rand(n + 1, *S, generator=g))


def box(seed=0):
    g = torch.Generator().manual_seed(seed)
    centre = torch.randn(*S, generator=g)
    radius = 0.1 * torch.rand(*S, generator=g)
    return Box(centre - radius, centre + radius)


def instance(kind):
    if kind == "conv":
        return conv_net(), ArgmaxSpec([4, 2], [1, 0])
    net = TwoKeypointNet()
    return net, net.spec()


@pytest.mark.parametrize("kind", ["conv", "cellpool"])
@pytest.mark.parametrize("set_kind", ["hull", "box"])
def test_onnx_matches_torch(tmp_path, kind, set_kind):
    model, spec = instance(kind)
    input_set = hull(3) if set_kind == "hull" else box()
    info = export_instance(tmp_path / "inst", model, input_set, spec)
    assert info["onnx"].is_file() and info["vnnlib"].is_file()
    assert (info["n_outputs"], info["n_disjuncts"]) == (spec.n_outputs, spec.n_rows)
    sess = ort.InferenceSession(str(info["onnx"]), providers=["CPUExecutionProvider"])
    (inp,) = sess.get_inputs()
    if set_kind == "hull":
        assert (inp.name, inp.shape) == ("lam", [1, 3])
        points = input_set.sample(5, seed=1)
        images = input_set.image(points)
    else:
        assert (inp.name, inp.shape) == ("x", [1, *S])
        points = images = input_set.sample(5, seed=1)
    for p, x in zip(points, images):
        got = sess.run(["y"], {inp.name: p[None].float().numpy()})[0]
        with torch.no_grad():
            want = model(x[None]).flatten(1).numpy()
        assert got.shape == (1, spec.n_outputs)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-4)
    # constants are folded: F.pad's pads are an initializer, not a Slice/Concat chain
    proto = onnx.load(info["onnx"])
    onnx.checker.check_model(proto, full_check=True)
    graph = proto.graph
    initializers = {t.name for t in graph.initializer}
    assert not {"Constant", "ConstantOfShape", "Transpose"} & {n.op_type for n in graph.node}
    assert all(n.input[1] in initializers for n in graph.node if n.op_type == "Pad")


@pytest.mark.parametrize(("n", "cls"), [(3, ConvexHull), (3, Parallelotope), (1, ConvexHull)])
def test_vnnlib_encodes_the_instance(tmp_path, n, cls):
    model = TwoKeypointNet()
    spec = model.spec(keep_b=False)
    input_set = hull(n, cls=cls)
    info = export_instance(tmp_path, model, input_set, spec)
    poly = read_vnnlib_polytope(info["vnnlib"])
    assert (poly["n_inputs"], poly["n_outputs"]) == (n, spec.n_outputs)
    np.testing.assert_array_equal(poly["lower"], np.zeros(n))
    np.testing.assert_array_equal(poly["upper"], np.ones(n))
    if cls is ConvexHull and n > 1:
        ((coeffs, rhs),) = poly["constraints"]
        np.testing.assert_array_equal(coeffs, np.ones(n))
        assert rhs == 1.0
    else:  # a parallelotope, or a 1-simplex (Σλ ≤ 1 is the bound X_0 ≤ 1)
        assert poly["constraints"] == []
    # the parsed polytope is the set's parameter domain
    lam = np.random.default_rng(0).uniform(-0.2, 1.2, (200, n))
    inside = ((lam >= poly["lower"]) & (lam <= poly["upper"])).all(1)
    for coeffs, rhs in poly["constraints"]:
        inside &= lam @ coeffs <= rhs
    np.testing.assert_array_equal(inside, input_set.contains_lambda(torch.from_numpy(lam)).numpy())
    # one clause Y_neg >= Y_pos per margin row; the excluded group has none
    pairs = list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))
    assert poly["disjuncts"] == pairs and info["n_disjuncts"] == len(pairs) > 0
    excluded = range(spec.offsets[1], spec.offsets[2])
    assert not any(j in excluded or t in excluded for j, t in pairs)
    y = torch.randn(100, spec.n_outputs)
    violated = torch.stack([y[:, j] >= y[:, t] for j, t in poly["disjuncts"]], 1).any(1)
    assert torch.equal(violated, (spec.margins(y) <= 0).any(1))


def test_box_bounds_round_trip(tmp_path):
    model, spec = instance("conv")
    input_set = box(seed=3)
    info = export_instance(tmp_path, model, input_set, spec)
    poly = read_vnnlib_polytope(info["vnnlib"])
    assert info["n_inputs"] == poly["n_inputs"] == int(np.prod(S))
    np.testing.assert_array_equal(poly["lower"], input_set.lower.double().reshape(-1).numpy())
    np.testing.assert_array_equal(poly["upper"], input_set.upper.double().reshape(-1).numpy())
    assert poly["constraints"] == []
    assert poly["disjuncts"] == list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))


def test_spec_mismatch_writes_nothing(tmp_path):
    out = tmp_path / "inst"
    with pytest.raises(ValueError, match="spec"):
        export_instance(out, conv_net(), hull(2), ArgmaxSpec([4, 3], [1, 0]))
    with pytest.raises(ValueError, match="spec"):
        export_instance(out, conv_net(), hull(2), ArgmaxSpec([4, 2], [None, None]))
    assert not out.exists()


def test_bad_arguments(tmp_path):
    path = tmp_path / "taken"
    path.write_text("")
    spec = ArgmaxSpec([4, 2], [1, 0])
    with pytest.raises(ValueError, match="directory"):
        export_instance(path, conv_net(), hull(2), spec)
    with pytest.raises(ValueError, match="input_set"):
        export_instance(tmp_path / "a", conv_net(), torch.zeros(3, *S), spec)
    with pytest.raises(ValueError, match="spec"):
        export_instance(tmp_path / "a", conv_net(), hull(2), [4, 2])
    assert list(tmp_path.iterdir()) == [path]


class Unexportable(nn.Module):
    """Runs in torch, but has no ONNX form (an SVD)."""

    def forward(self, x):
        return torch.linalg.svdvals(x.flatten(1).reshape(1, 12, 16))[:, :6]


def test_export_failure_leaves_no_files(tmp_path):
    with pytest.raises(ValueError, match="model"):
        export_instance(tmp_path, Unexportable(), hull(2), ArgmaxSpec([6], [0]))
    assert list(tmp_path.iterdir()) == []
