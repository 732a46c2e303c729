"""Export a verification instance as ONNX + VNN-LIB, the VNN-COMP exchange format.

:func:`export_instance` writes two files so that other verifiers (alpha-beta-CROWN, NNV,
ModelVerification.jl, …) can run the very instance this package checks:

``model.onnx``
    For a :class:`~kpstudy.verify.sets.ConvexHull` or
    :class:`~kpstudy.verify.sets.Parallelotope`, the network with the affine map
    ``λ ↦ X0 + λ D`` folded in as a leading layer: input ``lam`` of shape ``(1, n)``,
    so the input set is a polytope in ``n`` variables rather than in pixel space. For a
    :class:`~kpstudy.verify.sets.Box`, the plain network on ``x`` of shape ``(1, *S)``.
    Output ``y`` of shape ``(1, m)``, the model's output flattened.
``spec.vnnlib``
    The input set and the *violation* of the :class:`~kpstudy.verify.spec.ArgmaxSpec`
    (VNN-COMP asks for the negation of the property: ``unsat`` means verified). Inputs:
    ``0 ≤ λ_i ≤ 1`` plus, for the hull, ``Σ λ ≤ 1`` (a linear input constraint, which
    only some verifiers accept); the parallelotope ``[0, 1]^n`` is what MV.jl verifies
    instead; a box gives per-pixel bounds ``X_i`` in C order. Output: one disjunction
    with a clause ``Y_j ≥ Y_t`` per margin row of the spec.

:func:`read_vnnlib_polytope` reads back exactly the subset of VNN-LIB written here.
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

from kpstudy.io import atomic_path
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.spec import ArgmaxSpec


class _Instance(nn.Module):
    """``model(X0 + lam @ D)`` flattened to ``(B, m)``; without directions, ``model(x)``."""

    def __init__(self, model: nn.Module, input_set) -> None:
        super().__init__()
        self.model = copy.deepcopy(model).float().eval()
        self.shape = input_set.shape
        self.affine = isinstance(input_set, ConvexHull)
        if self.affine:
            n = input_set.n
            self.register_buffer("origin", input_set.origin.reshape(1, -1).float())
            self.register_buffer("directions", input_set.directions.reshape(n, -1).float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.affine:
            x = (self.origin + x @ self.directions).reshape(-1, *self.shape)
        return self.model(x).flatten(1)


def export_instance(directory, model: nn.Module, input_set, spec: ArgmaxSpec, *, opset=17):
    """Write ``model.onnx`` and ``spec.vnnlib`` for one verification instance.

    Parameters
    ----------
    directory : str or Path
        Output folder, created if missing; existing files of the same names are replaced.
    model : nn.Module
        The network on images ``(B, *S)``; exported in float32, eval mode (a copy: the
        module itself is left untouched).
    input_set : ConvexHull, Parallelotope or Box
        The input set; a hull or parallelotope is exported over ``λ`` (``n`` inputs), a box
        over its ``prod(S)`` pixels.
    spec : ArgmaxSpec
        The property; ``spec.n_outputs`` must be the model's flattened output size and at
        least one group must have a target.
    opset : int
        ONNX opset version.

    Returns
    -------
    dict
        ``onnx``, ``vnnlib`` (Paths), ``n_inputs``, ``n_outputs`` and ``n_disjuncts`` (the
        margin rows, one clause each).

    Raises
    ------
    ValueError
        If ``directory`` is an existing file, ``input_set`` is of another type, ``spec``
        does not fit the model's output or has no verified group, or ``model`` fails to run
        or to export. Nothing is written then (files go to temporary names first).
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
    wrapper = _Instance(model, input_set)
    if isinstance(input_set, Box):
        name, example = "x", input_set.lower[None].float()
    else:
        name, example = "lam", torch.zeros(1, input_set.n)
    try:
        with torch.no_grad():
            n_out = wrapper(example).shape[1]
    except Exception as exc:
        raise ValueError(f"model: failed on the input set's first point: {exc}") from exc
    spec.check_output(n_out)
    text = _vnnlib_text(input_set, spec, name)

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
    }


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


def _vnnlib_text(input_set, spec: ArgmaxSpec, name: str) -> str:
    n, m = input_set.n, spec.n_outputs
    kind = type(input_set).__name__
    if isinstance(input_set, Box):
        meaning = f"X_i = pixel i of x (shape (1, {', '.join(map(str, input_set.shape))}), C order)"
        lower = input_set.lower.double().reshape(-1).tolist()
        upper = input_set.upper.double().reshape(-1).tolist()
    else:
        meaning = "X_i = lambda_i, image = X0 + lam @ D inside model.onnx"
        lower, upper = [0.0] * n, [1.0] * n
    lines = [
        f"; kpstudy verification instance: {kind} input set, n = {n}",
        f"; inputs: model.onnx '{name}', {meaning}",
        f"; outputs: model.onnx 'y' (1, {m}), {spec.n_groups} groups "
        f"{spec.group_sizes}, targets {spec.targets}",
        f"; {spec.n_rows} margin rows; the assertions state a violation (unsat = verified)",
        "",
        *(f"(declare-const X_{i} Real)" for i in range(n)),
        *(f"(declare-const Y_{j} Real)" for j in range(m)),
        "",
    ]
    for i in range(n):
        lines += [f"(assert (>= X_{i} {lower[i]!r}))", f"(assert (<= X_{i} {upper[i]!r}))"]
    if isinstance(input_set, ConvexHull) and not isinstance(input_set, Parallelotope) and n > 1:
        # Σλ ≤ 1; for n = 1 it is the bound X_0 ≤ 1 already
        lines.append(f"(assert (<= (+ {' '.join(f'X_{i}' for i in range(n))}) 1.0))")
    lines += ["", "(assert (or"]
    lines += [
        f"  (and (>= Y_{j} Y_{t}))" for j, t in zip(spec.row_neg.tolist(), spec.row_pos.tolist())
    ]
    lines.append("))")
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
