"""The box → simplex layer of exported instances (kpstudy.verify.simplex_map)."""

import numpy as np
import onnx
import pytest
import torch

from kpstudy.verify.export import _export_onnx
from kpstudy.verify.sets import ConvexHull
from kpstudy.verify.simplex_map import BoxToSimplex, SimplexWeights, box_of_lambda, lambda_of_box


@pytest.mark.parametrize("n", range(1, 7))
def test_every_box_point_lands_in_the_simplex(n):
    """Sampled u (uniform, on the box's faces and corners) give the sorted spacings: λ ≥ 0,
    Σλ ≤ 1, w = (1 − Σλ, λ); exact in float64, to rounding in float32."""
    g = torch.Generator().manual_seed(n)
    u = torch.rand(2000, n, generator=g, dtype=torch.float64)
    u[:500] = u[:500].round()  # corners
    u[500:1000, 0] = u[500:1000, 0].round()  # faces
    w = BoxToSimplex(n, torch.float64)(u)
    lam = lambda_of_box(u)
    torch.testing.assert_close(w[:, 1:], lam, rtol=0, atol=1e-15)
    assert (lam >= 0).all() and (lam.sum(1) <= 1 + 1e-15).all()
    torch.testing.assert_close(w.sum(1), torch.ones(2000, dtype=torch.float64), rtol=0, atol=1e-15)
    w32 = BoxToSimplex(n)(u.float())
    assert w32.dtype == torch.float32
    torch.testing.assert_close(w32.double(), w, rtol=0, atol=1e-6)


@pytest.mark.parametrize("n", range(1, 7))
def test_every_simplex_point_is_the_image_of_a_box_point(n):
    """Vertices, edge midpoints and Dirichlet samples of the simplex: u = cumsum(λ) lies in
    [0, 1]^n and maps to λ."""
    hull = ConvexHull(torch.zeros(n + 1, 1))
    corners = torch.cat([torch.zeros(1, n), torch.eye(n)]).double()
    i, j = np.triu_indices(n + 1, 1)
    lam = torch.cat([corners, 0.5 * (corners[i] + corners[j]), hull.sample(500, seed=n)])
    u = box_of_lambda(lam)
    assert ((u >= 0) & (u <= 1 + 1e-15)).all()
    w = BoxToSimplex(n, torch.float64)(u)
    torch.testing.assert_close(w[:, 1:], lam, rtol=0, atol=1e-15)


@pytest.mark.parametrize("cls", [BoxToSimplex, SimplexWeights])
def test_layers_export_as_matmul_relu_add_only(tmp_path, cls):
    path = tmp_path / "map.onnx"
    _export_onnx(cls(4), torch.zeros(1, 4), "u", str(path), 17)
    ops = {node.op_type for node in onnx.load(path).graph.node}
    assert ops <= {"MatMul", "Relu", "Add"}


@pytest.mark.parametrize("n", [2, 3, 4])
def test_spacings_read_a_relu(tmp_path, n):
    """The sorted u passes a Relu before the spacings' MatMul: fed by the sort's last Add
    (two sources), Marabou 2.0.0 counted the next bias twice."""
    path = tmp_path / "map.onnx"
    _export_onnx(BoxToSimplex(n), torch.zeros(1, n), "u", str(path), 17)
    nodes = onnx.load(path).graph.node
    made_by = {out: node.op_type for node in nodes for out in node.output}
    (spacing,) = [node for node in nodes if "spacing" in node.input]
    assert made_by[spacing.input[0]] == "Relu"


def test_bad_dimension_is_named():
    with pytest.raises(ValueError, match="n: expected an integer >= 1"):
        BoxToSimplex(0)
    with pytest.raises(ValueError, match="n: expected"):
        SimplexWeights(2.0)
