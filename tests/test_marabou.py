"""Marabou (maraboupy) as a test oracle for kpstudy.verify.verify on exported instances.

Small keypoint-like proxies (a conv backbone, two heatmap channels, each pooled into its
keypoint's cells) over hulls of n = 1…4 perturbed images are exported in both input forms
(*simplex*: ``λ ≥ 0``, ``Σ λ ≤ 1`` in the VNN-LIB file; *box*: ``u ∈ [0, 1]^n`` and the
ReLU sorting layer in the ONNX) and handed to Marabou as ONNX + VNN-LIB, its own readers.
Every instance Marabou decides must agree with ``verify``, and each of its
counterexamples, mapped back to ``λ``, must lie in the hull and have a float64 margin ≤ 0
on the torch model at the exact hull point, up to a solver tolerance.

Marabou 2.0.0's ONNX reader has no ``Pad``, ``AveragePool`` or ``Slice``, so the pooling
here is one ``Gemm`` (the cell pools' matrices, block-diagonal over the channels); the
xfail test below records that the study's own proxy is out of its reach, so that it flips
when Marabou reads it. The compact property form's worst-margin tree is made of
``Slice`` s too: the instances here (tests/helpers/tiny_proxies.py) are exported in the
full form (one disjunct per margin row), the same verdict
(tests/kpstudy/verify/test_export.py).
"""

from __future__ import annotations

import copy
import os
import time

import numpy as np
import pytest
import torch
from torch import nn

from kpstudy.verify import verify
from kpstudy.verify.export import export_instance, point_of_input
from tests.helpers.tiny_proxies import SIDE, make_instance

pytest.importorskip("maraboupy")

pytestmark = [
    pytest.mark.marabou,
    pytest.mark.filterwarnings("ignore:Tensorflow parser is unavailable:UserWarning"),
]

#: Counterexamples' float64 margins may exceed 0 by this much, times 1 + max |y(X0)|:
#: Marabou's points satisfy ``Y_j ≥ Y_t`` to its arithmetic's tolerance (boundary points
#: of +1e-16 were seen).
TOLERANCE = 1e-9
#: A ``sat`` answer whose own output values miss every clause by more than this (times
#: 1 + max |y(X0)|) is Marabou refuting itself, not a misreading of the network (in the
#: case seen its assignment met every equation and ReLU of the graph, only not the
#: disjunction; open Marabou issues 563 and 873): it counts as undecided.
SELF_REFUTING = 1e-4
#: Seconds Marabou gets per instance, generous so that its answers do not depend on the
#: machine's speed (an undecided instance counts against the test's ≥ 20 of 24): on two
#: busy cores box-form instances took up to 36 s (n = 4), simplex-form ones at most 4 s,
#: so the 30 s budget it had left a busier machine's box-form verdict to chance. Only a
#: hang (Marabou has ignored its timeout before: tests/marabou_worker.py) runs into it.
MARABOU_SECONDS = 300


@pytest.fixture(scope="module")
def marabou():
    from tests.marabou_worker import MarabouProcess

    process = MarabouProcess()
    yield process
    process.close()


@pytest.mark.parametrize("form", ["simplex", pytest.param("box", marks=pytest.mark.slow)])
def test_marabou_agrees_with_verify(tmp_path, marabou, form):
    """≥ 20 of 24 instances decided by Marabou (a self-refuting ``sat`` is no decision),
    every one as ``verify`` decides it (both answers among them), every counterexample a
    point of the hull that fails in float64."""
    rows = []
    for i in range(24):
        model, hull = make_instance(i)
        spec = model.spec
        start = time.perf_counter()
        ours = verify(model, hull, spec, timeout=600, max_nodes=1000)
        ours_time = time.perf_counter() - start
        info = export_instance(
            tmp_path / str(i), model, hull, spec, input_form=form, property_form="full"
        )
        code, x, y, seconds = marabou.solve(info["onnx"], info["vnnlib"], MARABOU_SECONDS)
        assert not code.startswith("error"), (i, code)
        double = copy.deepcopy(model).double()
        with torch.no_grad():
            scale = 1 + double(hull.vertices[:1].double()).abs().max().item()
        if code == "sat" and spec.margins(torch.tensor([y])).min() > SELF_REFUTING * scale:
            code = "self-refuting sat"
        rows.append((i, hull.n, ours.status, code, ours_time, seconds))
        if code in ("sat", "unsat"):
            assert {"sat": "violated", "unsat": "holds"}[code] == ours.status, rows[-1]
        if code == "sat":
            lam = point_of_input(hull, np.asarray([x]), form)
            assert hull.contains_lambda(lam, tol=TOLERANCE).all(), (i, lam)
            with torch.no_grad():
                margin = spec.margins(double(hull.image(lam, dtype=torch.float64))).min().item()
            assert margin <= TOLERANCE * scale, (i, margin, scale)
    decided = [r for r in rows if r[3] in ("sat", "unsat")]
    holds = sum(r[2] == "holds" for r in decided)
    refuting = sum(r[3] == "self-refuting sat" for r in rows)
    print(
        f"\nMarabou on {len(rows)} {form}-form instances: {len(decided)} decided "
        f"({holds} unsat/holds, {len(decided) - holds} sat/violated), all agreeing, "
        f"{refuting} self-refuting sat; "
        f"Marabou {sum(r[5] for r in rows):.2f} s in all (max {max(r[5] for r in rows):.2f} s), "
        f"verify {sum(r[4] for r in rows):.2f} s (max {max(r[4] for r in rows):.2f} s)"
    )
    assert len(decided) >= 20, rows
    assert holds >= 3 and len(decided) - holds >= 3, rows  # both answers are exercised


def _onnxruntime_and_marabou(path, x):
    import onnxruntime as ort
    from maraboupy import Marabou

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (inp,) = session.get_inputs()
    want = session.run(None, {inp.name: x})[0]
    options = Marabou.createOptions(verbosity=0, timeoutInSeconds=MARABOU_SECONDS)
    network = Marabou.read_onnx(str(path))
    got = network.evaluateWithMarabou([x], filename=os.devnull, options=options)[0]
    return np.asarray(want).ravel(), np.asarray(got).ravel()


def test_marabou_reads_the_box_form(tmp_path):
    """Marabou's own evaluation of box-form graphs equals onnxruntime's (n = 2, 3, 4): the
    Relu after the sort keeps its network-level reasoner from counting ``X0`` twice."""
    for i in (1, 2, 3):
        model, hull = make_instance(i)
        info = export_instance(
            tmp_path / str(i), model, hull, model.spec, input_form="box", property_form="full"
        )
        u = np.linspace(0.7, 0.2, hull.n, dtype=np.float32)[None]  # descending: every swap
        want, got = _onnxruntime_and_marabou(info["onnx"], u)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)


@pytest.mark.xfail(
    strict=True,
    raises=NotImplementedError,
    reason="Marabou 2.0.0's ONNX reader has no Slice, Pad or AveragePool: the study's "
    "KeypointProxy (channel slices, padded average pooling) cannot be read",
)
def test_marabou_reads_the_keypoint_proxy(tmp_path):
    from kpstudy.models.pooling import keypoint_pooling
    from kpstudy.models.proxy import build_proxy

    torch.manual_seed(0)
    backbone = nn.Sequential(nn.Conv2d(1, 2, 3, padding=1), nn.ReLU(), nn.Conv2d(2, 2, 1))
    centers = [(1, 2), (4, 3)]
    pooling = keypoint_pooling(centers, [(1, 1), (0, 1)], (SIDE, SIDE))
    proxy = build_proxy(backbone, pooling, centers, heatmap_size=(SIDE, SIDE))
    hull = make_instance(1)[1]
    info = export_instance(
        tmp_path, proxy.eval(), hull, proxy.spec, input_form="simplex", property_form="full"
    )
    want, got = _onnxruntime_and_marabou(info["onnx"], np.full((1, hull.n), 0.25, np.float32))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
