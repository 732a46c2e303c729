"""ONNX + VNN-LIB export of a verification instance (kpstudy.verify.export)."""

from types import SimpleNamespace

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from onnx import numpy_helper
from onnx.reference import ReferenceEvaluator
from torch import nn
from torch.nn import functional as F

from kpstudy.models.backbones import build_backbone
from kpstudy.models.pooling import build_cell_pool, keypoint_cells
from kpstudy.models.proxy import build_proxy
from kpstudy.verify import verify
from kpstudy.verify.export import (
    WorstMargins,
    export_instance,
    point_of_input,
    read_vnnlib_polytope,
)
from kpstudy.verify.ops import cell_pool
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


def worst_margins(spec, y):
    """Each group's least margin ``(B, G)`` from outputs ``y (B, m)``, over the groups with
    margin rows: what the compact form's graph computes, here from the spec's rows."""
    groups = sorted(set(spec.row_group.tolist()))
    return spec.group_min(spec.margins(torch.as_tensor(y)))[:, groups].numpy()


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
@pytest.mark.parametrize("prop", ["compact", "full"])
def test_onnx_matches_torch(tmp_path, kind, set_kind, form, dtype, prop):
    """ONNX (onnxruntime) equals the torch model on the set's points (the full form's
    output; the compact form's: each group's least margin), float32 to 1e-4, float64 to
    1e-10; the box input form maps u onto λ by the sorted spacings."""
    model, spec = instance(kind)
    input_set = {"hull": hull(3), "cube": hull(3, cls=Parallelotope), "box": box()}[set_kind]
    info = export_instance(
        tmp_path / "inst", model, input_set, spec, input_form=form, dtype=dtype, property_form=prop
    )
    assert info["onnx"].is_file() and info["vnnlib"].is_file()
    sizes = (spec.n_outputs, spec.n_rows) if prop == "full" else (spec.n_groups,) * 2
    assert (info["n_outputs"], info["n_disjuncts"], info["property_form"]) == (*sizes, prop)
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
        if prop == "compact":
            want = worst_margins(spec, want)
        assert got.shape == (1, info["n_outputs"]) and got.dtype == want.dtype
        np.testing.assert_allclose(
            got, want, rtol=0, atol=1e-4 if dtype == torch.float32 else 1e-10
        )
    # constants are folded (F.pad's pads leave no Slice/Concat chain), and the cell pools'
    # zero padding (rows asymmetric: 2 and 0 or 1 and 0) is a one-hot depthwise Conv
    proto = onnx.load(info["onnx"])
    onnx.checker.check_model(proto, full_check=True)
    ops = [n.op_type for n in proto.graph.node]
    assert not {"Constant", "ConstantOfShape", "Transpose", "Pad"} & set(ops)
    assert ops.count("Conv") == {"conv": 1, "cellpool": 3}[kind]


class PaddedPool(nn.Module):
    """A ``(1, C, 5, 7)`` map padded by ``F.pad`` (``value`` or ``mode``), flattened, then
    its cell pool (:func:`kpstudy.verify.ops.cell_pool`, which pads it with zeros)."""

    def __init__(self, pad, kernel, value=0.0, mode="constant"):
        super().__init__()
        self.pad, self.kernel, self.value, self.mode = pad, kernel, value, mode

    def forward(self, x):
        value = self.value if self.mode == "constant" else None
        padded = F.pad(x, self.pad, mode=self.mode, value=value)
        pooled = cell_pool(x, self.pad, self.kernel, torch.full((1, 1), 0.5))
        return torch.cat([padded.flatten(1), pooled.flatten(1)], 1)


def padded_pool_instance(tmp_path, model, channels, dtype=torch.float32):
    """``model`` exported over a box of ``(channels, 5, 7)`` maps: the ONNX graph's nodes,
    its initializers, and its session's outputs and the torch model's at 4 points."""
    g = torch.Generator().manual_seed(3)
    lower = torch.randn(channels, 5, 7, generator=g)
    input_set = Box(lower, lower + torch.rand(channels, 5, 7, generator=g))
    x = input_set.sample(4, seed=5).to(dtype)
    with torch.no_grad():
        want = model(x).numpy()
    spec = ArgmaxSpec([want.shape[1]], [0])
    info = export_instance(tmp_path, model, input_set, spec, dtype=dtype, property_form="full")
    proto = onnx.load(info["onnx"])
    sess = _session(info["onnx"], dtype)
    got = np.concatenate([sess.run(["y"], {"x": p[None].numpy()})[0] for p in x])
    weights = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
    return list(proto.graph.node), weights, got, want


@pytest.mark.parametrize(
    ("pad", "kernel"),
    [
        ((0, 2, 3, 1), (3, 3)),
        ((2, 0, 1, 4), (5, 3)),
        ((1, 1, 0, 2), (7, 3)),
        ((0, 0, 2, 2), (3, 7)),
    ],
)
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_padding_is_a_one_hot_convolution(tmp_path, pad, kernel, channels, dtype):
    """Each ``Pad`` of zeros (pads ``(left, right, top, bottom)``, asymmetric along either
    axis or both, or symmetric) becomes a depthwise ``Conv`` with symmetric pads and a one-hot
    kernel, which NeuralSAT's auto_LiRPA bounds and the onnx2pytorch of NeuralSAT and
    α,β-CROWN converts as is (asymmetric ``pads`` it gets wrong): no ``Pad`` is left, the
    padded map is the torch model's exactly and the cell pool's to rounding (onnxruntime
    in float32, onnx's reference evaluator in float64)."""
    model = PaddedPool(pad, kernel).to(dtype)
    nodes, weights, got, want = padded_pool_instance(tmp_path, model, channels, dtype)
    convs = [n for n in nodes if n.op_type == "Conv"]
    assert "Pad" not in {n.op_type for n in nodes} and len(convs) == 1  # one F.pad, traced once
    left, right, top, bottom = pad
    p, q = max(top, bottom), max(left, right)
    for conv in convs:
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in conv.attribute}
        assert attrs["pads"] == [p, q, p, q] and attrs["group"] == channels
        assert attrs["strides"] == [1, 1]
        one_hot = np.zeros((channels, 1, 1 + abs(top - bottom), 1 + abs(left - right)))
        one_hot[:, :, p - top, q - left] = 1
        np.testing.assert_array_equal(weights[conv.input[1]], one_hot)
        assert weights[conv.input[1]].dtype == want.dtype
    assert got.dtype == want.dtype
    size = channels * (5 + top + bottom) * (7 + left + right)
    np.testing.assert_array_equal(got[:, :size], want[:, :size])
    tolerance = 1e-6 if dtype == torch.float32 else 1e-14
    np.testing.assert_allclose(got[:, size:], want[:, size:], rtol=0, atol=tolerance)


@pytest.mark.parametrize(("value", "mode"), [(1.0, "constant"), (0.0, "reflect")])
def test_other_padding_stays_a_pad(tmp_path, value, mode):
    """A ``Pad`` of another value or mode is no zero padding: it stays, beside the cell
    pool's zero padding made a ``Conv``."""
    model = PaddedPool((0, 2, 3, 1), (3, 3), value=value, mode=mode)
    nodes, _, got, want = padded_pool_instance(tmp_path, model, 2)
    ops = [n.op_type for n in nodes]
    assert ops.count("Pad") == 1 and ops.count("Conv") == 1
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("form", ["box", "simplex"])
def test_hull_vertices_are_exported_exactly(tmp_path, form):
    """The hull's corners give its vertices bit for bit (no rounded X_i − X0), in both
    input forms: a Flatten model's output is the image itself."""
    input_set = hull(3, seed=4)
    spec = ArgmaxSpec([int(np.prod(S))], [0])
    info = export_instance(
        tmp_path, nn.Flatten(), input_set, spec, input_form=form, property_form="full"
    )
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
@pytest.mark.parametrize("prop", ["compact", "full"])
def test_vnnlib_encodes_the_instance(tmp_path, n, cls, form, prop):
    model = TwoKeypointNet()
    spec = model.spec(keep_b=False)
    input_set = hull(n, cls=cls)
    info = export_instance(tmp_path, model, input_set, spec, input_form=form, property_form=prop)
    poly = read_vnnlib_polytope(info["vnnlib"])
    outputs = spec.n_outputs if prop == "full" else 1  # the compact form: group a's margin
    assert (poly["n_inputs"], poly["n_outputs"], info["n_outputs"]) == (n, outputs, outputs)
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
    y = torch.randn(100, spec.n_outputs, generator=torch.Generator().manual_seed(n))
    y[:, spec.row_pos[0]] += 2.0  # group a's target wins in most rows, but not all
    y[::3, spec.row_neg[2]] = y[::3, spec.row_pos[2]]  # ties: violations in both forms
    if prop == "full":  # one clause Y_neg >= Y_pos per margin row; the excluded group has none
        pairs = list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))
        assert poly["disjuncts"] == pairs and info["n_disjuncts"] == len(pairs) > 0
        excluded = range(spec.offsets[1], spec.offsets[2])
        assert not any(j in excluded or t in excluded for j, t in pairs)
        violated = torch.stack([y[:, j] >= y[:, t] for j, t in poly["disjuncts"]], 1).any(1)
    else:  # one clause 0 >= Y_g per group with margin rows: group a's
        assert poly["disjuncts"] == [(None, 0)] and info["n_disjuncts"] == 1
        z = WorstMargins(spec)(y)
        violated = torch.stack([z[:, g] <= 0 for _, g in poly["disjuncts"]], 1).any(1)
    assert violated[::3].all() and not violated.all()
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
    assert poly["disjuncts"] == [(None, 0), (None, 1)]  # the compact form: one per group


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
    with pytest.raises(ValueError, match="^property_form: expected one of"):
        export_instance(tmp_path / "a", conv_net(), hull(2), spec, property_form="min")
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
@pytest.mark.parametrize("prop", ["compact", "full"])
def test_vnnlib_2_parses_with_the_vnnlib_package(tmp_path, set_kind, form, dtype, prop):
    """The VNN-LIB 2.0 file parses with the `vnnlib` package; where every input constraint
    is a bound, its VNN-COMP reachability form has the set's box and one output polytope
    per disjunct: ``Y_t − Y_j ≤ 0`` per margin row (full form), ``Y_g ≤ 0`` per group
    (compact form)."""
    vnnlib = pytest.importorskip("vnnlib")
    compat = pytest.importorskip("vnnlib.compat")

    model, spec = instance("cellpool")
    input_set = {"hull": hull(3), "cube": hull(3, cls=Parallelotope), "box": box()}[set_kind]
    info = export_instance(
        tmp_path,
        model,
        input_set,
        spec,
        input_form=form,
        dtype=dtype,
        vnnlib_version="2.0",
        property_form=prop,
    )
    query = vnnlib.parse_query_file(str(info["vnnlib"]))
    ((x,),) = [net.inputs for net in query.networks]
    ((y,),) = [net.outputs for net in query.networks]
    kind = vnnlib.DType.F64 if dtype == torch.float64 else vnnlib.DType.F32
    assert (x.dtype, y.dtype) == (kind, kind)
    assert list(x.shape) == ([1, *S] if set_kind == "box" else [1, 3])
    assert list(y.shape) == [1, info["n_outputs"]]
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
        assert list(poly.rhs) == [0.0]
        if prop == "compact":
            assert list(coeffs[coeffs != 0]) == [1.0]
            rows.append(int(np.flatnonzero(coeffs)[0]))
            continue
        assert sorted(coeffs[coeffs != 0]) == [-1.0, 1.0]
        rows.append((int(np.flatnonzero(coeffs == -1)[0]), int(np.flatnonzero(coeffs == 1)[0])))
    if prop == "compact":
        assert rows == list(range(spec.n_groups))
    else:
        assert rows == list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))


def study_proxy(name, keypoints, seed=0):
    """The study's 64×64 heatmap CNN ``name`` (random weights; batch norms with random
    statistics and affine parameters) under cell pooling, ``keypoints`` random keypoints
    in cells of side 2 or 3 (about 10^3 cells per keypoint, as the allocation's)."""
    torch.manual_seed(seed)
    backbone = build_backbone(name, keypoints)
    for m in backbone.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            nn.init.uniform_(m.weight, 0.5, 1.5)
            nn.init.uniform_(m.bias, -0.5, 0.5)
    rng = np.random.default_rng(seed)
    centers = rng.integers(0, 64, (keypoints, 2))
    cells = keypoint_cells(centers, centers + rng.integers(1, 3, (keypoints, 2)), (64, 64))
    return build_proxy(backbone, cells, centers).eval()


def input_bn_net():
    """A batch norm on the input (it follows no convolution), then :func:`conv_net`."""
    torch.manual_seed(1)
    bn = nn.BatchNorm2d(3)
    bn.running_mean.uniform_(-0.5, 0.5)
    bn.running_var.uniform_(0.5, 2.0)
    return nn.Sequential(bn, conv_net()).eval()


def importer_faults(path) -> list[str]:
    """What ONNX importers trip on in the graph at ``path``: a ``BatchNormalization`` node
    or a ``training_mode`` attribute (onnx2pytorch: "Extraction of attribute training_mode
    not implemented"), a symbolic dimension on a declared input or output or on any value
    after strict shape inference (NeuralSAT took ``Flatteny_dim_0/1`` for (1, 1)), an
    omitted (``''``) node input (read as the network input for the Pad value), a ``Pad``
    (NeuralSAT 0.2.17's auto_LiRPA fails to bound it: "BoundPad.forward() missing 1
    required positional argument: 'pad'") or asymmetric ``pads`` on another node
    (onnx2pytorch pads with rows and columns swapped), a ``Gather`` (onnx2pytorch follows
    it by a ``Squeeze`` whose backward bounds auto_LiRPA gets wrong: NeuralSAT 0.2.17
    failed to bound the first compact graphs) or a ``Slice`` with steps (onnx2pytorch
    ignores them), and what the full checker refuses."""
    model = onnx.load(path)
    nodes = model.graph.node
    refused = ("BatchNormalization", "Gather")
    faults = [f"{n.op_type} {n.name}" for n in nodes if n.op_type in refused]
    constants = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    faults += [
        f"steps on {n.name}"
        for n in nodes
        if n.op_type == "Slice" and len(n.input) > 4 and (constants[n.input[4]] != 1).any()
    ]
    faults += [
        f"training_mode on {n.name}"
        for n in nodes
        for a in n.attribute
        if a.name == "training_mode"
    ]
    faults += [f"omitted input of {n.op_type} {n.name}" for n in nodes if "" in n.input]
    faults += [f"Pad {n.name}" for n in nodes if n.op_type == "Pad"]
    faults += [
        f"asymmetric pads on {n.name}"
        for n in nodes
        for a in n.attribute
        if a.name == "pads" and a.ints[: len(a.ints) // 2] != a.ints[len(a.ints) // 2 :]
    ]
    values = [*model.graph.input, *model.graph.output]
    try:
        inferred = onnx.shape_inference.infer_shapes(model, strict_mode=True).graph
        values += [*inferred.input, *inferred.output, *inferred.value_info]
    except onnx.shape_inference.InferenceError as exc:
        faults.append(f"shape inference: {exc}")
    for v in values:
        if not all(d.HasField("dim_value") for d in v.type.tensor_type.shape.dim):
            faults.append(f"symbolic shape of {v.name}: {v.type.tensor_type.shape}")
    try:
        onnx.checker.check_model(model, full_check=True)
    except onnx.checker.ValidationError as exc:
        faults.append(f"checker: {exc}")
    return faults


@pytest.mark.parametrize("arch", ["cnn", "cnn_patch_smooth", "input_bn"])
@pytest.mark.parametrize("prop", ["compact", "full"])
def test_exported_graph_is_portable(tmp_path, arch, prop):
    """The study's CNNs (batch norms after transposed convolutions, which the exporter
    does not fold) under 23-keypoint cell pooling (its zero padding a ``Conv``, ``Slice``)
    over a hull, and a batch norm that follows no convolution: no importer fault
    (:func:`importer_faults`), and onnxruntime still gives the torch model's outputs at
    the hull's vertices and samples. The compact form's VNN-LIB has one disjunct per
    keypoint, in a few kilobytes."""
    if arch == "input_bn":
        model, spec, shape = input_bn_net(), ArgmaxSpec([4, 2], [1, 0]), S
    else:
        model = study_proxy(arch, 23)
        spec, shape = model.spec, (3, 64, 64)
    g = torch.Generator().manual_seed(2)
    x0 = torch.rand(1, *shape, generator=g)
    input_set = ConvexHull(torch.cat([x0, x0 + 0.1 * torch.randn(2, *shape, generator=g)]))
    info = export_instance(tmp_path, model, input_set, spec, property_form=prop)
    assert importer_faults(info["onnx"]) == []
    sess = _session(info["onnx"])
    lam = torch.cat([torch.zeros(1, 2), torch.eye(2), input_set.sample(3, seed=4)]).double()
    with torch.no_grad():
        want = model(input_set.image(lam, dtype=torch.float32)).flatten(1).double()
    if prop == "compact":
        want = torch.from_numpy(worst_margins(spec, want))
    for u, y in zip(box_of_lambda(lam), want):
        got = sess.run(["y"], {"u": u[None].float().numpy()})[0][0]
        np.testing.assert_allclose(got, y, rtol=1e-4, atol=1e-4 * want.abs().max().item())
    if arch != "input_bn":
        size = info["vnnlib"].stat().st_size
        if prop == "compact":  # measured: 2.2 kB (the full form: 0.86 MB, 15,388 clauses)
            assert info["n_disjuncts"] == spec.n_groups == 23 and size < 3000
        else:
            assert info["n_disjuncts"] == spec.n_rows > 10_000 and size > 500_000


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_worst_margins_are_the_least_margin_rows(dtype):
    """Groups of 1 to 18 rows (each padded with copies to 32, one group without
    rows, one without a target): each column of :class:`WorstMargins` is its group's
    least margin row, and it is ``≤ 0`` exactly where a row is, ties (a margin of
    exactly 0, a violation for ``verify``) included."""
    spec = ArgmaxSpec([1, 3, 7, 2, 18, 5, 4], [0, 1, 6, None, 3, 4, 0])
    tree = WorstMargins(spec)
    assert tree.groups == [1, 2, 4, 5, 6]
    g = torch.Generator().manual_seed(0)
    y = torch.randn(400, spec.n_outputs, generator=g, dtype=dtype)
    y[:, spec.row_pos.unique()] += 2.0  # most groups' targets win, some do not
    tied = torch.randint(spec.n_rows, (200,), generator=g)
    y[torch.arange(200), spec.row_neg[tied]] = y[torch.arange(200), spec.row_pos[tied]]
    z = tree(y)
    want = spec.group_min(spec.margins(y))[:, tree.groups]
    assert (want == 0).any() and (want > 0).any() and (want < 0).any()
    assert torch.equal(z <= 0, want <= 0)
    torch.testing.assert_close(z, want, rtol=0, atol=8 * torch.finfo(dtype).eps * y.abs().max())
    assert tree.width == 32 and tree.pos.shape == tree.neg.shape == (5 * 32,)
    dense = DenseWorstMargins(nn.Identity(), spec).to(dtype)  # the same tree, as Linear layers
    torch.testing.assert_close(dense(y)[:, ::2], z, rtol=0, atol=0)


@pytest.mark.parametrize("kind", ["conv", "cellpool"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compact_graph_gives_the_full_graphs_worst_margins(tmp_path, kind, dtype):
    """At the hull's vertices and Dirichlet samples, the compact graph's outputs are the
    least margins ``Y_t − Y_j`` of the full graph's outputs, per group (onnxruntime in
    float32, onnx's reference evaluator in float64)."""
    model, spec = instance(kind)
    input_set = hull(3, seed=5)
    runs = {}
    for prop in ("compact", "full"):
        info = export_instance(
            tmp_path / prop, model, input_set, spec, dtype=dtype, property_form=prop
        )
        runs[prop] = _session(info["onnx"], dtype)
    lam = torch.cat([torch.zeros(1, 3), torch.eye(3), input_set.sample(20, seed=6)]).double()
    for u in box_of_lambda(lam):
        feed = {"u": u[None].to(dtype).numpy()}
        full, compact = (runs[p].run(["y"], feed)[0] for p in ("full", "compact"))
        want = worst_margins(spec, full)
        tol = 8 * torch.finfo(dtype).eps * np.abs(full).max()
        np.testing.assert_allclose(compact, want, rtol=0, atol=tol)
        assert np.array_equal(compact <= 0, want <= 0)


class DenseWorstMargins(nn.Module):
    """``net`` then :class:`WorstMargins`'s very tree (its padded blocks and halving levels)
    as operators :func:`kpstudy.verify.verify` traces: ``Linear`` layers of 0/±1 matrices,
    ``relu`` and ``+``. Output ``(B, 2G)``: each group's least margin ``z_g``, then a
    constant 0, so that ``ArgmaxSpec([2] * G, [0] * G)`` states "every ``z_g > 0``"."""

    def __init__(self, net, spec):
        super().__init__()
        tree = WorstMargins(spec)
        groups = len(tree.groups)
        self.net = net
        self.margins = self.select(spec.n_outputs, tree.pos, tree.neg)
        self.levels = nn.ModuleList()
        width = tree.width
        while width > 1:  # each block's first half against its second
            width //= 2
            first = torch.cat([g * 2 * width + torch.arange(width) for g in range(groups)])
            negate = nn.Linear(len(first), len(first), bias=False)
            nn.init.constant_(negate.weight, 0.0)
            negate.weight.data.fill_diagonal_(-1.0)
            whole = groups * 2 * width
            level = [self.select(whole, first), self.select(whole, first, first + width), negate]
            self.levels.append(nn.ModuleList(level))
        self.pad = nn.Linear(groups, 2 * groups, bias=False)  # z_g → (z_g, 0)
        nn.init.constant_(self.pad.weight, 0.0)
        self.pad.weight.data[::2] = torch.eye(groups)
        self.spec = ArgmaxSpec([2] * groups, [0] * groups)
        self.eval()

    @staticmethod
    def select(width, plus, minus=None):
        """``v ↦ v[plus] − v[minus]`` (or ``v[plus]``) as a ``Linear`` on ``(B, width)``."""
        layer = nn.Linear(width, len(plus))
        nn.init.constant_(layer.weight, 0.0)
        nn.init.constant_(layer.bias, 0.0)
        rows = torch.arange(len(plus))
        layer.weight.data[rows, plus] = 1.0
        if minus is not None:
            layer.weight.data[rows, minus] -= 1.0
        return layer

    def forward(self, x):
        v = self.margins(self.net(x))
        for first, diff, negate in self.levels:
            v = first(v) + negate(torch.relu(diff(v)))
        return self.pad(v)


class Lifted(nn.Module):
    """``net`` with each group's target raised so that ``x0`` has least margin ``margin``
    in every group (a ``Linear`` of identity weights and that bias): small hulls around
    ``x0`` hold, wide ones do not."""

    def __init__(self, net, spec, x0, margin=0.05):
        super().__init__()
        self.net = net
        self.lift = nn.Linear(spec.n_outputs, spec.n_outputs)
        with torch.no_grad():
            self.lift.weight.copy_(torch.eye(spec.n_outputs))
            self.lift.bias.zero_()
            least = spec.group_min(spec.margins(self(x0)))[0]
            for g in spec.active_groups:
                self.lift.bias[spec.offsets[g] + spec.targets[g]] = margin - least[g]
        self.eval()

    def forward(self, x):
        return self.lift(self.net(x))


def test_compact_and_full_give_the_same_verdict(tmp_path):
    """kpstudy's ``verify`` decides every instance the same on the proxy's margin rows
    (the full form) and on the compact form's tree (:class:`DenseWorstMargins`), both
    verdicts among them; at a counterexample both exported graphs (float64) state a
    violation, at the points of a hull that holds neither does."""
    verdicts = []
    for i, spread in enumerate([0.01, 0.03, 0.3, 1.0, 0.02, 0.5]):
        net = TwoKeypointNet(seed=i)
        g = torch.Generator().manual_seed(i)
        x0 = torch.rand(1, *S, generator=g)
        model = Lifted(net, net.spec(), x0)
        spec = net.spec()
        input_set = ConvexHull(torch.cat([x0, x0 + spread * torch.randn(2, *S, generator=g)]))
        full = verify(model, input_set, spec, timeout=600, max_nodes=2000)
        dense = DenseWorstMargins(model, spec)
        compact = verify(dense, input_set, dense.spec, timeout=600, max_nodes=2000)
        assert full.status == compact.status != "unknown", (i, full.status, compact.status)
        verdicts.append(full.status)
        runs = {}
        for prop in ("compact", "full"):
            info = export_instance(
                tmp_path / f"{i}{prop}",
                model,
                input_set,
                spec,
                dtype=torch.float64,
                property_form=prop,
            )
            runs[prop] = _session(info["onnx"], torch.float64)
        if full.status == "violated":
            lam = full.counterexample.point[None].double()
        else:
            lam = torch.cat([torch.eye(2), input_set.sample(30, seed=i)]).double()
        for u in box_of_lambda(lam):
            feed = {"u": u[None].numpy()}
            y, z = (runs[p].run(["y"], feed)[0][0] for p in ("full", "compact"))
            violated = (spec.margins(torch.from_numpy(y[None])) <= 1e-12).any().item()
            assert violated == (z.min() <= 1e-12) == (full.status == "violated")
    assert set(verdicts) == {"holds", "violated"}
