"""ONNX + VNN-LIB export of a verification instance (kpstudy.verify.export)."""

from types import SimpleNamespace

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx.reference import ReferenceEvaluator
from torch import nn

from kpstudy.models.pooling import build_cell_pool
from kpstudy.verify.export import export_instance, point_of_input, read_vnnlib_polytope
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.simplex_map import box_of_lambda
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


class _Reference:
    """onnx's reference evaluator behind onnxruntime's ``get_inputs`` / ``run`` (onnxruntime
    has no float64 ``Conv`` on the CPU)."""

    def __init__(self, path):
        self.proto = onnx.load(path)
        self.evaluator = ReferenceEvaluator(self.proto)

    def get_inputs(self):
        (inp,) = self.proto.graph.input
        kind = onnx.helper.tensor_dtype_to_np_dtype(inp.type.tensor_type.elem_type)
        dims = [d.dim_value for d in inp.type.tensor_type.shape.dim]
        name = {np.float32: "tensor(float)", np.float64: "tensor(double)"}[kind.type]
        return [SimpleNamespace(name=inp.name, shape=dims, type=name)]

    def run(self, outputs, feeds):
        return self.evaluator.run(outputs, feeds)


def _session(path, dtype=torch.float32):
    """onnxruntime for float32, onnx's reference evaluator for float64."""
    if dtype == torch.float64:
        return _Reference(path)
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("kind", ["conv", "cellpool"])
@pytest.mark.parametrize(
    ("set_kind", "form"), [("hull", "box"), ("hull", "simplex"), ("cube", "box"), ("box", "box")]
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_onnx_matches_torch(tmp_path, kind, set_kind, form, dtype):
    """ONNX (onnxruntime) equals the torch model on the set's points: float32 to 1e-4,
    float64 to 1e-10; the box input form maps u onto λ by the sorted spacings."""
    model, spec = instance(kind)
    input_set = {"hull": hull(3), "cube": hull(3, cls=Parallelotope), "box": box()}[set_kind]
    info = export_instance(tmp_path / "inst", model, input_set, spec, input_form=form, dtype=dtype)
    assert info["onnx"].is_file() and info["vnnlib"].is_file()
    assert (info["n_outputs"], info["n_disjuncts"]) == (spec.n_outputs, spec.n_rows)
    sess = _session(info["onnx"], dtype)
    (inp,) = sess.get_inputs()
    name = {"hull": "u" if form == "box" else "lam", "cube": "lam", "box": "x"}[set_kind]
    shape = [1, *S] if set_kind == "box" else [1, 3]
    assert (inp.name, inp.shape, info["input_name"]) == (name, shape, name)
    assert inp.type == ("tensor(double)" if dtype == torch.float64 else "tensor(float)")
    points = input_set.sample(5, seed=1)
    inputs = box_of_lambda(points) if name == "u" else points
    np.testing.assert_allclose(
        point_of_input(input_set, inputs.reshape(5, -1).numpy(), form), points, atol=1e-15
    )
    images = input_set.image(points, dtype=dtype)
    for p, x in zip(inputs, images):
        got = sess.run(["y"], {inp.name: p[None].to(dtype).numpy()})[0]
        with torch.no_grad():
            want = model.to(dtype)(x[None]).flatten(1).numpy()
        assert got.shape == (1, spec.n_outputs) and got.dtype == want.dtype
        np.testing.assert_allclose(
            got, want, rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-10
        )
    # constants are folded: F.pad's pads are an initializer, not a Slice/Concat chain
    proto = onnx.load(info["onnx"])
    onnx.checker.check_model(proto, full_check=True)
    graph = proto.graph
    initializers = {t.name for t in graph.initializer}
    assert not {"Constant", "ConstantOfShape", "Transpose"} & {n.op_type for n in graph.node}
    assert all(n.input[1] in initializers for n in graph.node if n.op_type == "Pad")


@pytest.mark.parametrize("form", ["box", "simplex"])
def test_hull_vertices_are_exported_exactly(tmp_path, form):
    """The hull's corners give its vertices bit for bit (no rounded X_i − X0), in both
    input forms: a Flatten model's output is the image itself."""
    input_set = hull(3, seed=4)
    spec = ArgmaxSpec([int(np.prod(S))], [0])
    info = export_instance(tmp_path, nn.Flatten(), input_set, spec, input_form=form)
    sess = _session(info["onnx"])
    corners = torch.cat([torch.zeros(1, 3), torch.eye(3)]).double()
    inputs = box_of_lambda(corners) if form == "box" else corners
    for k, p in enumerate(inputs):
        got = sess.run(["y"], {info["input_name"]: p[None].float().numpy()})[0]
        np.testing.assert_array_equal(got[0], input_set.vertices[k].reshape(-1).numpy())


@pytest.mark.parametrize(
    ("n", "cls", "form"),
    [
        (3, ConvexHull, "simplex"),
        (3, ConvexHull, "box"),
        (3, Parallelotope, "simplex"),
        (1, ConvexHull, "simplex"),
    ],
)
def test_vnnlib_encodes_the_instance(tmp_path, n, cls, form):
    model = TwoKeypointNet()
    spec = model.spec(keep_b=False)
    input_set = hull(n, cls=cls)
    info = export_instance(tmp_path, model, input_set, spec, input_form=form)
    poly = read_vnnlib_polytope(info["vnnlib"])
    assert (poly["n_inputs"], poly["n_outputs"]) == (n, spec.n_outputs)
    np.testing.assert_array_equal(poly["lower"], np.zeros(n))
    np.testing.assert_array_equal(poly["upper"], np.ones(n))
    if cls is ConvexHull and n > 1 and form == "simplex":
        ((coeffs, rhs),) = poly["constraints"]
        np.testing.assert_array_equal(coeffs, np.ones(n))
        assert rhs == 1.0
    else:  # the box form, a parallelotope, or a 1-simplex (Σλ ≤ 1 is the bound X_0 ≤ 1)
        assert poly["constraints"] == []
    # the parsed polytope, mapped to the set's parameter, is the set's parameter domain
    x = np.random.default_rng(0).uniform(-0.2, 1.2, (200, n))
    inside = ((x >= poly["lower"]) & (x <= poly["upper"])).all(1)
    for coeffs, rhs in poly["constraints"]:
        inside &= x @ coeffs <= rhs
    if form == "box" and cls is ConvexHull:  # the box [0, 1]^n, mapped onto the simplex
        lam = point_of_input(input_set, x[inside], form)
        assert inside.sum() > 10 and input_set.contains_lambda(lam, tol=1e-15).all()
    else:
        lam = torch.from_numpy(x)
        np.testing.assert_array_equal(inside, input_set.contains_lambda(lam).numpy())
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
    with pytest.raises(ValueError, match="input_form"):
        export_instance(tmp_path / "a", conv_net(), hull(2), spec, input_form="lam")
    with pytest.raises(ValueError, match="dtype"):
        export_instance(tmp_path / "a", conv_net(), hull(2), spec, dtype=torch.float16)
    with pytest.raises(ValueError, match="vnnlib_version"):
        export_instance(tmp_path / "a", conv_net(), hull(2), spec, vnnlib_version="3")
    assert list(tmp_path.iterdir()) == [path]


class Unexportable(nn.Module):
    """Runs in torch, but has no ONNX form (an SVD)."""

    def forward(self, x):
        return torch.linalg.svdvals(x.flatten(1).reshape(1, 12, 16))[:, :6]


def test_export_failure_leaves_no_files(tmp_path):
    with pytest.raises(ValueError, match="model"):
        export_instance(tmp_path, Unexportable(), hull(2), ArgmaxSpec([6], [0]))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("set_kind", "form"), [("hull", "box"), ("hull", "simplex"), ("cube", "box"), ("box", "box")]
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vnnlib_2_parses_with_the_vnnlib_package(tmp_path, set_kind, form, dtype):
    """The VNN-LIB 2.0 file parses with the `vnnlib` package; where every input constraint
    is a bound, its VNN-COMP reachability form has the set's box and one output polytope
    ``Y_t − Y_j ≤ 0`` per margin row."""
    vnnlib = pytest.importorskip("vnnlib")
    compat = pytest.importorskip("vnnlib.compat")

    model, spec = instance("cellpool")
    input_set = {"hull": hull(3), "cube": hull(3, cls=Parallelotope), "box": box()}[set_kind]
    info = export_instance(
        tmp_path, model, input_set, spec, input_form=form, dtype=dtype, vnnlib_version="2.0"
    )
    query = vnnlib.parse_query_file(str(info["vnnlib"]))
    ((x,),) = [net.inputs for net in query.networks]
    ((y,),) = [net.outputs for net in query.networks]
    kind = vnnlib.DType.F64 if dtype == torch.float64 else vnnlib.DType.F32
    assert (x.dtype, y.dtype) == (kind, kind)
    assert list(x.shape) == ([1, *S] if set_kind == "box" else [1, 3])
    assert list(y.shape) == [1, spec.n_outputs]
    if set_kind == "hull" and form == "simplex":  # Σ λ ≤ 1: not a bound
        assert len(query.assertions) == 2 * 3 + 2
        with pytest.raises(vnnlib.VNNLibException, match="simple bounds"):
            compat.transform(query)
        return
    (case,) = compat.transform(query)
    if set_kind == "box":
        lower, upper = (b.double().reshape(-1).numpy() for b in (input_set.lower, input_set.upper))
    else:
        lower, upper = np.zeros(3), np.ones(3)
    np.testing.assert_array_equal(np.array(case.input_box), np.stack([lower, upper], 1))
    rows = []
    for poly in case.output_constraints:
        (coeffs,) = np.array(poly.coeff_matrix)
        assert list(poly.rhs) == [0.0] and sorted(coeffs[coeffs != 0]) == [-1.0, 1.0]
        rows.append((int(np.flatnonzero(coeffs == -1)[0]), int(np.flatnonzero(coeffs == 1)[0])))
    assert rows == list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))
