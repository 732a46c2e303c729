"""Export a verification instance as ONNX + VNN-LIB, the VNN-COMP exchange format.

:func:`export_instance` writes two files so that other verifiers (alpha-beta-CROWN, NNV,
PyRAT, Marabou, …) can run the very instance this package checks:

``model.onnx``
    For a :class:`~kpstudy.verify.sets.ConvexHull`, the network with the hull folded in
    as leading layers that map the input onto the barycentric weights ``w`` of the
    ``n + 1`` vertices, then ``image = w @ V`` with the vertices ``V`` themselves (so the
    set is exactly their hull in real arithmetic, not that of rounded directions):

    * ``input_form='box'`` (default): input ``u`` of shape ``(1, n)`` in ``[0, 1]^n``,
      mapped onto the simplex by :class:`~kpstudy.verify.simplex_map.BoxToSimplex` (a
      sort by a ReLU min/max network, then the spacings), so that any verifier that
      accepts box inputs runs the exact hull;
    * ``input_form='simplex'``: input ``lam`` of shape ``(1, n)`` with ``λ ≥ 0`` and the
      linear input constraint ``Σ λ ≤ 1`` (only some verifiers accept it).

    A :class:`~kpstudy.verify.sets.Parallelotope` takes ``lam`` in the cube ``[0, 1]^n``;
    a :class:`~kpstudy.verify.sets.Box` the plain network on ``x`` of shape ``(1, *S)``.
    Output ``y`` of shape ``(1, m)``, the model's output flattened. float32 by default,
    float64 with ``dtype=torch.float64`` (the model and the vertices converted).
``spec.vnnlib``
    The input set and the *violation* of the :class:`~kpstudy.verify.spec.ArgmaxSpec`
    (VNN-COMP asks for the negation of the property: ``unsat`` means verified), one
    clause ``Y_j ≥ Y_t`` per margin row in a disjunction. ``vnnlib_version='1.0'``: the
    form of the VNN-COMPs (``declare-const X_i Real``, inputs flattened in C order);
    ``'2.0'``: the VNN-LIB 2.0 standard (``declare-network`` with typed, shaped tensors
    ``X`` and ``Y``; numbers in positional notation, as its grammar asks).

:func:`read_vnnlib_polytope` reads back exactly the VNN-LIB 1.0 subset written here;
:func:`point_of_input` maps an assignment of the ONNX input (a verifier's
counterexample) to the set's own point (``λ``, or the image of a box).
"""

from __future__ import annotations

import copy
import re
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper
from onnx.reference import ReferenceEvaluator
from torch import nn
from torch.nn import functional as F

from kpstudy.io import atomic_path
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.simplex_map import BoxToSimplex, SimplexWeights, lambda_of_box
from kpstudy.verify.spec import ArgmaxSpec

INPUT_FORMS = ("box", "simplex")
VNNLIB_VERSIONS = ("1.0", "2.0")
DTYPES = {torch.float32: "float32", torch.float64: "float64"}


class _Instance(nn.Module):
    """``model(w(x) @ V)`` flattened to ``(B, m)`` for a hull (``w``: the input's
    barycentric weights); ``model(x)`` for a box."""

    def __init__(self, model: nn.Module, input_set, input_form: str, dtype) -> None:
        super().__init__()
        self.model = copy.deepcopy(model).to(dtype).eval()
        self.shape = input_set.shape
        self.hull = isinstance(input_set, ConvexHull)
        if self.hull:
            n = input_set.n
            if _form(input_set, input_form) == "box" and not isinstance(input_set, Parallelotope):
                self.weights = BoxToSimplex(n, dtype)
            else:
                self.weights = SimplexWeights(n, dtype)
            self.register_buffer("vertices", input_set.vertices.reshape(n + 1, -1).to(dtype))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.hull:  # w @ V = (w − e_0) @ V + X0 as one Gemm with a bias
            x = F.linear(self.weights.linear(x), self.vertices.T, self.vertices[0])
            x = x.reshape(-1, *self.shape)
        return self.model(x).flatten(1)


def _form(input_set, input_form: str) -> str:
    """What the exported input is: ``'box'`` (``[0, 1]^n``: a hull's box form or a
    parallelotope), ``'simplex'`` (``λ`` with ``Σ λ ≤ 1``) or ``'pixels'`` (a Box set)."""
    if isinstance(input_set, Box):
        return "pixels"
    if isinstance(input_set, Parallelotope):
        return "box"
    return input_form


def export_instance(
    directory,
    model: nn.Module,
    input_set,
    spec: ArgmaxSpec,
    *,
    input_form: str = "box",
    dtype=torch.float32,
    vnnlib_version: str = "1.0",
    opset: int = 17,
):
    """Write ``model.onnx`` and ``spec.vnnlib`` for one verification instance.

    Parameters
    ----------
    directory : str or Path
        Output folder, created if missing; existing files of the same names are replaced.
    model : nn.Module
        The network on images ``(B, *S)``; exported in eval mode (a copy in ``dtype``: the
        module itself is left untouched).
    input_set : ConvexHull, Parallelotope or Box
        The input set; a hull or parallelotope is exported over ``n`` parameters, a box
        over its ``prod(S)`` pixels.
    spec : ArgmaxSpec
        The property; ``spec.n_outputs`` must be the model's flattened output size and at
        least one group must have a target.
    input_form : {'box', 'simplex'}
        A hull's input: ``u ∈ [0, 1]^n`` mapped exactly onto the simplex inside the
        network (default), or ``λ`` with the linear constraint ``Σ λ ≤ 1``. Ignored for a
        parallelotope and a box, whose inputs are boxes already.
    dtype : torch.float32 or torch.float64
        Precision of the ONNX graph (weights, vertices, input and output).
    vnnlib_version : {'1.0', '2.0'}
        VNN-LIB dialect: the VNN-COMP form (1.0) or the VNN-LIB 2.0 standard.
    opset : int
        ONNX opset version.

    Returns
    -------
    dict
        ``onnx``, ``vnnlib`` (Paths), ``n_inputs``, ``n_outputs``, ``n_disjuncts`` (the
        margin rows, one clause each), ``input_name`` (``'u'``, ``'lam'`` or ``'x'``),
        ``input_form`` (``'box'``, ``'simplex'`` or ``'pixels'``), ``dtype``
        (``'float32'`` / ``'float64'``) and ``vnnlib_version``.

    Raises
    ------
    ValueError
        If ``directory`` is an existing file, ``input_set`` is of another type,
        ``input_form``, ``dtype`` or ``vnnlib_version`` is not one of the above, ``spec``
        does not fit the model's output or has no verified group, or ``model`` fails to
        run or to export. Nothing is written then (files go to temporary names first).
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"directory: expected a folder, got the existing file {directory}")
    if not isinstance(input_set, ConvexHull | Box):
        raise ValueError(
            "input_set: expected a ConvexHull, Parallelotope or Box, got "
            f"{type(input_set).__name__}"
        )
    if not isinstance(model, nn.Module):
        raise ValueError(f"model: expected a torch.nn.Module, got {type(model).__name__}")
    if not isinstance(spec, ArgmaxSpec):
        raise ValueError(f"spec: expected an ArgmaxSpec, got {type(spec).__name__}")
    if spec.n_rows == 0:
        raise ValueError("spec: expected at least one group with a target, got none")
    if input_form not in INPUT_FORMS:
        raise ValueError(f"input_form: expected one of {INPUT_FORMS}, got {input_form!r}")
    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype!r}")
    if vnnlib_version not in VNNLIB_VERSIONS:
        raise ValueError(
            f"vnnlib_version: expected one of {VNNLIB_VERSIONS}, got {vnnlib_version!r}"
        )
    form = _form(input_set, input_form)
    wrapper = _Instance(model, input_set, input_form, dtype)
    if form == "pixels":
        name, example = "x", input_set.lower[None].to(dtype)
    else:
        box_input = form == "box" and not isinstance(input_set, Parallelotope)
        name, example = ("u" if box_input else "lam"), torch.zeros(1, input_set.n, dtype=dtype)
    try:
        with torch.no_grad():
            n_out = wrapper(example).shape[1]
    except Exception as exc:
        raise ValueError(f"model: failed on the input set's first point: {exc}") from exc
    spec.check_output(n_out)
    text = _vnnlib_text(input_set, spec, name, form, DTYPES[dtype], vnnlib_version)

    directory.mkdir(parents=True, exist_ok=True)
    onnx_path, vnnlib_path = directory / "model.onnx", directory / "spec.vnnlib"
    with atomic_path(onnx_path) as tmp_onnx, atomic_path(vnnlib_path) as tmp_vnnlib:
        _export_onnx(wrapper, example, name, tmp_onnx, opset)
        Path(tmp_vnnlib).write_text(text)
    return {
        "onnx": onnx_path,
        "vnnlib": vnnlib_path,
        "n_inputs": input_set.n,
        "n_outputs": spec.n_outputs,
        "n_disjuncts": spec.n_rows,
        "input_name": name,
        "input_form": form,
        "dtype": DTYPES[dtype],
        "vnnlib_version": vnnlib_version,
    }


def point_of_input(input_set, x, input_form: str = "box") -> torch.Tensor:
    """The set's point of an assignment ``x`` of the exported ONNX input, in float64.

    For a hull exported with ``input_form='box'``: ``λ`` = the spacings of the sorted
    ``u`` (``(…, n)``); with ``'simplex'``, and for a parallelotope, ``λ = x``; for a box,
    the image ``x`` reshaped to ``(…, *S)``. Feed the result to ``input_set.image(…,
    dtype=torch.float64)`` to get the exact image in float64.
    """
    if input_form not in INPUT_FORMS:
        raise ValueError(f"input_form: expected one of {INPUT_FORMS}, got {input_form!r}")
    x = torch.as_tensor(np.asarray(x), dtype=torch.float64)
    if isinstance(input_set, Box):
        return x.reshape(*x.shape[:-1], *input_set.shape)
    if _form(input_set, input_form) == "box" and not isinstance(input_set, Parallelotope):
        return lambda_of_box(x)
    return x


def export_onnx(model: nn.Module, example: torch.Tensor, path, *, opset=17) -> Path:
    """Write ``model`` (a float32 eval-mode copy) as ONNX with input ``x`` and output ``y``.

    ``example`` fixes the input shape, e.g. ``torch.zeros(1, 3, 64, 64)`` for the CNN
    backbone or its proxy. The file appears only when the export succeeded.

    Examples
    --------
    >>> export_onnx(build_backbone("cnn"), torch.zeros(1, 3, 64, 64), "cnn.onnx")  # doctest: +SKIP
    """
    if not isinstance(model, nn.Module):
        raise ValueError(f"model: expected a torch.nn.Module, got {type(model).__name__}")
    model = copy.deepcopy(model).float().eval()
    path = Path(path)
    with atomic_path(path) as tmp:
        _export_onnx(model, example.float(), "x", tmp, opset)
    return path


def read_vnnlib_polytope(path) -> dict:
    """Parse a ``spec.vnnlib`` written by :func:`export_instance` (only that subset).

    Returns
    -------
    dict
        ``lower``, ``upper`` : ndarray, shape (n,), float64 — input bounds (``∓inf`` where
        absent); ``constraints`` : list of ``(coeffs (n,), rhs)`` meaning
        ``coeffs · X ≤ rhs``; ``disjuncts`` : list of ``(neg, pos)`` meaning
        ``Y_neg ≥ Y_pos`` (the violation is any one of them); ``n_inputs``, ``n_outputs``.

    Raises
    ------
    ValueError
        On a line outside the subset.
    """
    decl = re.compile(r"\(declare-const ([XY])_(\d+) Real\)")
    bound = re.compile(r"\(assert \((<=|>=) X_(\d+) (\S+)\)\)")
    linear = re.compile(r"\(assert \(<= \(\+((?: X_\d+)+)\) (\S+)\)\)")
    clause = re.compile(r"\(and \(>= Y_(\d+) Y_(\d+)\)\)")
    count = {"X": 0, "Y": 0}
    bounds, sums, disjuncts = [], [], []
    for i, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith(";") or line in ("(assert (or", "))"):
            continue
        if m := decl.fullmatch(line):
            count[m[1]] = max(count[m[1]], int(m[2]) + 1)
        elif m := bound.fullmatch(line):
            bounds.append((m[1], int(m[2]), float(m[3])))
        elif m := linear.fullmatch(line):
            sums.append(([int(x) for x in re.findall(r"X_(\d+)", m[1])], float(m[2])))
        elif m := clause.fullmatch(line):
            disjuncts.append((int(m[1]), int(m[2])))
        else:
            raise ValueError(f"path: line {i} is outside the exported VNN-LIB subset: {line!r}")
    n = count["X"]
    lower, upper = np.full(n, -np.inf), np.full(n, np.inf)
    for op, k, value in bounds:
        (lower if op == ">=" else upper)[k] = value
    constraints = []
    for idx, rhs in sums:
        coeffs = np.zeros(n)
        coeffs[idx] = 1.0
        constraints.append((coeffs, rhs))
    return {
        "lower": lower,
        "upper": upper,
        "constraints": constraints,
        "disjuncts": disjuncts,
        "n_inputs": n,
        "n_outputs": count["Y"],
    }


def _number(x: float) -> str:
    """``x`` in positional notation with a point (``1.0``, ``-0.0625``, ``0.000001``), the
    shortest digits that read back as the same float64: VNN-LIB 2.0's grammar has no
    exponents, and VNN-COMP readers take it too."""
    return np.format_float_positional(float(x), unique=True, trim="0")


def _vnnlib_text(input_set, spec: ArgmaxSpec, name: str, form: str, dtype: str, version) -> str:
    n, m = input_set.n, spec.n_outputs
    kind = type(input_set).__name__
    if form == "pixels":
        shape = (1, *input_set.shape)
        meaning = f"X = pixels of x {shape}" + (
            ", flattened in C order" if version == "1.0" else ""
        )
        lower = input_set.lower.double().reshape(-1).tolist()
        upper = input_set.upper.double().reshape(-1).tolist()
    else:
        shape = (1, n)
        lower, upper = [0.0] * n, [1.0] * n
        meaning = {
            "box": f"X = u in [0, 1]^{n}; model.onnx sorts u (a ReLU min/max network) and "
            "maps it onto the simplex: lambda_1 = u_(1), lambda_i = u_(i) - u_(i-1), "
            "image = (1 - sum lambda) X0 + sum lambda_i X_i, exactly the hull",
            "simplex": "X = lambda, lambda >= 0 and sum lambda <= 1; image = (1 - sum lambda) "
            "X0 + sum lambda_i X_i",
        }[form]
        if isinstance(input_set, Parallelotope):
            meaning = "X = lambda in [0, 1]^n; image = X0 + sum lambda_i (X_i - X0)"
    header = [
        f"; kpstudy verification instance: {kind} input set, n = {n}, input form {form}",
        f"; inputs: model.onnx '{name}' {shape} {dtype}, {meaning}",
        f"; outputs: model.onnx 'y' (1, {m}), {spec.n_groups} groups "
        f"{spec.group_sizes}, targets {spec.targets}",
        f"; {spec.n_rows} margin rows; the assertions state a violation (unsat = verified)",
    ]
    rows = list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))
    simplex = form == "simplex" and n > 1  # Σλ ≤ 1; for n = 1 it is the bound X_0 ≤ 1 already
    if version == "1.0":
        x = [f"X_{i}" for i in range(len(lower))]
        y = [f"Y_{j}" for j in range(m)]
        lines = [
            *header,
            "",
            *(f"(declare-const {v} Real)" for v in x),
            *(f"(declare-const {v} Real)" for v in y),
            "",
        ]
        clauses = [f"  (and (>= {y[j]} {y[t]}))" for j, t in rows]
    else:
        x = [f"X[{', '.join(map(str, (0, *idx)))}]" for idx in np.ndindex(*shape[1:])]
        y = [f"Y[0, {j}]" for j in range(m)]
        lines = [
            "(vnnlib-version <2.0>)",
            *header,
            "",
            "(declare-network kpstudy",
            f"  (declare-input X {dtype} [{', '.join(map(str, shape))}])",
            f"  (declare-output Y {dtype} [1, {m}])",
            ")",
            "",
        ]
        clauses = [f"  (>= {y[j]} {y[t]})" for j, t in rows]
    for v, lo, hi in zip(x, lower, upper):
        lines += [f"(assert (>= {v} {_number(lo)}))", f"(assert (<= {v} {_number(hi)}))"]
    if simplex:
        lines.append(f"(assert (<= (+ {' '.join(x)}) 1.0))")
    lines += ["", "(assert (or", *clauses, "))"]
    return "\n".join(lines) + "\n"


def _export_onnx(wrapper: nn.Module, example, name: str, path: str, opset: int) -> None:
    """The TorchScript exporter first (needs no onnxscript), then the torch.export one;
    constants folded (see :func:`_fold_constants`)."""
    errors = []
    for dynamo in (False, True):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)  # legacy exporter notice
                warnings.filterwarnings("ignore", "Constant folding - Only steps=1", UserWarning)
                torch.onnx.export(
                    wrapper,
                    (example,),
                    path,
                    dynamo=dynamo,
                    external_data=False,
                    input_names=[name],
                    output_names=["y"],
                    opset_version=opset,
                )
            _fold_constants(path)
            return
        except Exception as exc:
            errors.append(f"{'dynamo' if dynamo else 'torchscript'} exporter: {exc}")
    raise ValueError("model: failed to export to ONNX (" + "; ".join(errors) + ")")


def _fold_constants(path: str) -> None:
    """Replace the nodes that depend only on constants by initializers, in place.

    The TorchScript exporter leaves ``F.pad``'s pads as a Constant/Slice/Concat/Transpose
    chain (its reversing Slice stops torch's own folding); verifiers' ONNX importers want
    a constant ``Pad`` input.
    """
    model = onnx.load(path)
    graph = model.graph
    opsets = {o.domain: o.version for o in model.opset_import}
    values = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    nodes = []
    for node in graph.node:
        inputs = [x for x in node.input if x]
        if node.domain or not all(x in values for x in inputs):
            nodes.append(node)
            continue
        outputs = ReferenceEvaluator(node, opsets=opsets).run(None, {x: values[x] for x in inputs})
        values.update(zip(node.output, outputs))
    used = {x for node in nodes for x in node.input} | {o.name for o in graph.output}
    graph.ClearField("node")
    graph.node.extend(nodes)
    graph.ClearField("initializer")
    graph.initializer.extend(
        numpy_helper.from_array(np.asarray(v), k) for k, v in values.items() if k in used
    )
    onnx.save(model, path)
