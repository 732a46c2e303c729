"""Export a verification instance as ONNX + VNN-LIB, the VNN-COMP exchange format.

:func:`export_instance` writes two files so that other verifiers (alpha-beta-CROWN,
NeuralSAT, NNV, PyRAT, Marabou, …) can run the very instance this package checks:

``model.onnx``
    For a :class:`~kpstudy.verify.sets.ConvexHull`, the network with the hull folded in
    as leading layers that map the input onto the barycentric weights ``w`` of the
    ``n + 1`` vertices, then ``image = w @ V`` with the vertices ``V`` themselves (so the
    set is exactly their hull in real arithmetic, not that of rounded directions):

    * ``input_form='box'`` (default): input ``u`` of shape ``(1, n)`` in ``[0, 1]^n``,
      mapped onto the simplex by ``kpstudy.verify.simplex_map.BoxToSimplex`` (a
      sort by a ReLU min/max network, then the spacings), so that any verifier that
      accepts box inputs runs the exact hull;
    * ``input_form='simplex'``: input ``lam`` of shape ``(1, n)`` with ``λ ≥ 0`` and the
      linear input constraint ``Σ λ ≤ 1`` (only some verifiers accept it).

    A :class:`~kpstudy.verify.sets.Parallelotope` takes ``lam`` in the cube ``[0, 1]^n``;
    a :class:`~kpstudy.verify.sets.Box` the plain network on ``x`` of shape ``(1, *S)``.
    Output ``y``: with ``property_form='compact'`` (default) shape ``(1, G)``, one worst
    margin per group with margin rows (:class:`WorstMargins`); with ``'full'`` shape
    ``(1, m)``, the model's output flattened. float32 by default, float64 with
    ``dtype=torch.float64`` (the model and the vertices converted).

    The graph is one that ONNX importers take (onnx2pytorch, which alpha-beta-CROWN and
    NeuralSAT use, among them): batch norms folded into the convolutions before them (or
    a per-channel ``Mul``/``Add`` where none is), so no ``BatchNormalization`` node;
    static shapes on every value, batch 1 (no symbolic dimension); every node input
    named; constants folded; zero padding (``F.pad``, the cell pool's) is no ``Pad`` node
    but a depthwise ``Conv`` with a one-hot kernel and symmetric ``pads``
    (``_pad_as_conv()``; NeuralSAT 0.2.17's auto_LiRPA cannot bound a ``Pad``, and
    onnx2pytorch turns a ``Conv``'s or ``AveragePool``'s asymmetric ``pads`` into a wrong
    padding), a ``Pad`` of another value or mode stays one; it passes
    ``onnx.checker.check_model(full_check=True)`` and strict shape inference.
``spec.vnnlib``
    The input set and the *violation* of the :class:`~kpstudy.verify.spec.ArgmaxSpec`
    (VNN-COMP asks for the negation of the property: ``unsat`` means verified), a
    disjunction of one-constraint clauses: ``Y_g ≤ 0`` per group (compact form), or
    ``Y_j ≥ Y_t`` per margin row (full form). ``vnnlib_version='1.0'``: the form of the
    VNN-COMPs (``declare-const X_i Real``, inputs flattened in C order); ``'2.0'``: the
    VNN-LIB 2.0 standard (``declare-network`` with typed, shaped tensors ``X`` and
    ``Y``; numbers in positional notation, as its grammar asks).

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
from torch.nn.modules.batchnorm import _BatchNorm
from torch.nn.modules.conv import _ConvNd, _ConvTransposeNd
from torch.nn.utils.fusion import fuse_conv_bn_eval

from kpstudy import _checks
from kpstudy.io import atomic_path
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.simplex_map import BoxToSimplex, SimplexWeights, lambda_of_box
from kpstudy.verify.spec import ArgmaxSpec

INPUT_FORMS = ("box", "simplex")
VNNLIB_VERSIONS = ("1.0", "2.0")
PROPERTY_FORMS = ("compact", "full")
DTYPES = {torch.float32: "float32", torch.float64: "float64"}


class WorstMargins(nn.Module):
    """``y (B, m) ↦ z (B, G)``: per group with margin rows, its worst margin
    ``z_g = min_{j ≠ t_g} (y[t_g] − y[j])`` (``t_g``: the target, ``j``: the group's other
    rows), for the groups of ``spec.row_group`` in order (``groups``).

    The margins are :meth:`~kpstudy.verify.spec.ArgmaxSpec.margins`' rows (the same
    floating-point numbers: ``y[t] − y[j]``), their minimum a ReLU tree,
    ``min(a, b) = a − relu(a − b)``. Each group's rows are padded with copies of
    themselves to ``L`` (``width``, the least power of two ≥ every group's row count;
    ``_pad()``), the ``G`` blocks reshaped to ``(B, G, L)``, and each of the ``log2 L``
    levels takes the minimum of the block's two halves, entry by entry. Padding leaves
    each minimum as it is (copies only); it makes the second half of a block a copy of
    the first wherever a group has run out of rows, so that the tree's extra pairs are
    ``(a, a)``, a ReLU of exactly 0 for a verifier's linear bounds. The cost: ``G·L``
    entries, for a 64×64 study instance (23 keypoints of up to 4,095 rows, 38,691 in
    all) 94,208.

    The ONNX graph is ``Slice``, ``Sub`` (the target broadcast against its group's other
    cells), ``Concat``, ``Reshape`` and ``Relu``. No ``Gather``: NeuralSAT 0.2.17's
    onnx2pytorch follows one by a ``Squeeze`` whose backward bounds its auto_LiRPA gets
    wrong, and its forward bounds take a single index only (the first form of this tree,
    a ``Gather`` per level, failed to load there); no strided ``Slice`` either, whose step
    that onnx2pytorch ignores. Nodes: about 3 ``Slice`` and ``log2`` of the group's row
    count ``Concat`` per group, then 2 ``Slice``, 2 ``Sub`` and a ``Relu`` per level.

    Ties and rounding: ``z_g ≤ 0`` exactly when a margin row of ``g`` is ``≤ 0`` in real
    arithmetic. In floating point a row ``≤ 0`` still gives ``z_g ≤ 0`` (rounding is
    monotone: ``a − (a − b) ≤ 0`` for ``b ≤ 0 < a``), so a tie is a violation as in
    :func:`kpstudy.verify.bab.verify`; the tree can only add a violation, ``z_g = 0`` where
    a positive row is below half a unit in the last place of its partner.

    Attributes
    ----------
    groups : list of int
        The group of each output column.
    width : int
        ``L``, the padded row count of every group.
    pos, neg : LongTensor, shape (G·L,)
        The padded blocks, group after group: entry ``g·L + i`` is
        ``y[pos[g·L + i]] − y[neg[g·L + i]]``, a margin row of group ``groups[g]``.
    """

    def __init__(self, spec: ArgmaxSpec) -> None:
        super().__init__()
        rows = spec.row_group.tolist()
        self.groups = list(dict.fromkeys(rows))
        self.width = 1 << (max(rows.count(g) for g in self.groups) - 1).bit_length()
        #: per group: (offset of its outputs, their count, the target's index among them)
        self.blocks = [(spec.offsets[g], spec.group_sizes[g], spec.targets[g]) for g in self.groups]
        selected = [(spec.row_group == g, rows.count(g)) for g in self.groups]
        self.pos = torch.cat([_pad(spec.row_pos[r][None], c, self.width)[0] for r, c in selected])
        self.neg = torch.cat([_pad(spec.row_neg[r][None], c, self.width)[0] for r, c in selected])

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        padded = []
        for start, count, target in self.blocks:
            t = start + target
            parts = [y[:, a:b] for a, b in ((start, t), (t + 1, start + count)) if b > a]
            others = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
            padded.append(_pad(y[:, t : t + 1] - others, count - 1, self.width))
        v = torch.cat(padded, 1).reshape(-1, len(self.groups), self.width)
        half = self.width
        while half > 1:
            half //= 2
            first = v[:, :, :half]
            v = first - torch.relu(first - v[:, :, half:])
        return v.flatten(1)


def _pad(v: torch.Tensor, count: int, width: int) -> torch.Tensor:
    """``v (B, count)``, ``1 ≤ count ≤ width`` (a power of two), padded to ``(B, width)`` with
    copies of its columns: for ``count ≤ width/2`` two copies of ``v`` padded to
    ``width/2``, else ``v`` then its first ``width − count`` columns (a ``Concat`` of
    ``Slice`` s in ONNX)."""
    if 2 * count <= width:
        half = _pad(v, count, width // 2)
        return torch.cat([half, half], 1)
    return v if count == width else torch.cat([v, v[:, : width - count]], 1)


class _Instance(nn.Module):
    """``model(w(x) @ V)`` flattened to ``(B, m)`` for a hull (``w``: the input's
    barycentric weights); ``model(x)`` for a box; then, once :attr:`margins` is set to a
    :class:`WorstMargins`, those ``(B, G)``."""

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
        self.margins: WorstMargins | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.hull:  # w @ V = (w − e_0) @ V + X0 as one Gemm with a bias
            x = F.linear(self.weights.linear(x), self.vertices.T, self.vertices[0])
            x = x.reshape(-1, *self.shape)
        y = self.model(x).flatten(1)
        return y if self.margins is None else self.margins(y)


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
    property_form: str = "compact",
    opset: int = 17,
):
    """Write ``model.onnx`` and ``spec.vnnlib`` for one verification instance.

    The property has two forms; both state the same violation (the same verdict):

    * ``'compact'`` (default): the graph ends in :class:`WorstMargins`, output ``y`` of
      shape ``(1, G)``: per group with margin rows (a verified keypoint), the least of
      its margins ``y_t − y_j``, the minimum a ReLU tree in the graph. The VNN-LIB file
      has one disjunct ``Y_g ≤ 0`` per group, ``G ≤`` the number of keypoints (23 for
      the airliner): a few kilobytes. This is the form for VNN-COMP tools: their VNN-LIB
      readers cost time and memory per disjunct (alpha-beta-CROWN keeps an input copy
      per clause, NeuralSAT's parser took 32 s and 14 GB for the ~2·10^4 clauses of the
      full form), and the tree is ``Slice``, ``Sub``, ``Concat``, ``Reshape`` and
      ``Relu``, which their ONNX importers and bounds take (no ``Gather``: see
      :class:`WorstMargins`) and their branch and bound can split like any other ReLU.
      One instance per keypoint would still leave a clause per cell (~10^3) in
      each, and 23 files per hull.
    * ``'full'``: output ``y`` of shape ``(1, m)``, the model's flattened output, and one
      disjunct ``Y_j ≥ Y_t`` per margin row: every row a linear function of ``y``, no
      tree to relax, for verifiers that cope with ~10^4 disjuncts (and Marabou 2.0.0,
      whose ONNX reader has no ``Slice``).

    Ties are violations in both, as in :func:`kpstudy.verify.bab.verify` (a margin of
    exactly 0 is not verified): ``Y_g = 0`` is a violation as ``Y_j = Y_t`` is. In real
    arithmetic ``Y_g ≤ 0`` exactly when some row of group ``g`` has ``Y_j ≥ Y_t``; in
    floating point a row ``≤ 0`` still gives ``Y_g ≤ 0`` (see :class:`WorstMargins`).

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
    property_form : {'compact', 'full'}
        The property's form (above).
    opset : int
        ONNX opset version.

    Returns
    -------
    dict
        ``onnx``, ``vnnlib`` (Paths), ``n_inputs``, ``n_outputs`` (of the ONNX graph:
        ``G`` compact, ``m`` full), ``n_disjuncts`` (``G`` or the margin rows, one clause
        each), ``input_name`` (``'u'``, ``'lam'`` or ``'x'``), ``input_form`` (``'box'``,
        ``'simplex'`` or ``'pixels'``), ``dtype`` (``'float32'`` / ``'float64'``),
        ``vnnlib_version`` and ``property_form``.

    Raises
    ------
    ValueError
        If ``directory`` is an existing file, ``input_set`` is of another type,
        ``input_form``, ``dtype``, ``vnnlib_version`` or ``property_form`` is not one of
        the above, ``spec``
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
    _checks.choice(input_form, "input_form", INPUT_FORMS)
    if dtype not in DTYPES:
        raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype!r}")
    _checks.choice(vnnlib_version, "vnnlib_version", VNNLIB_VERSIONS)
    _checks.choice(property_form, "property_form", PROPERTY_FORMS)
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
    if property_form == "compact":
        wrapper.margins = WorstMargins(spec)
    text = _vnnlib_text(input_set, spec, name, form, DTYPES[dtype], vnnlib_version, wrapper.margins)

    directory.mkdir(parents=True, exist_ok=True)
    onnx_path, vnnlib_path = directory / "model.onnx", directory / "spec.vnnlib"
    with atomic_path(onnx_path) as tmp_onnx, atomic_path(vnnlib_path) as tmp_vnnlib:
        _export_onnx(wrapper, example, name, tmp_onnx, opset)
        Path(tmp_vnnlib).write_text(text)
    n_clauses = spec.n_rows if wrapper.margins is None else len(wrapper.margins.groups)
    return {
        "onnx": onnx_path,
        "vnnlib": vnnlib_path,
        "n_inputs": input_set.n,
        "n_outputs": spec.n_outputs if wrapper.margins is None else n_clauses,
        "n_disjuncts": n_clauses,
        "input_name": name,
        "input_form": form,
        "dtype": DTYPES[dtype],
        "vnnlib_version": vnnlib_version,
        "property_form": property_form,
    }


def point_of_input(input_set, x, input_form: str = "box") -> torch.Tensor:
    """The set's point of an assignment ``x`` of the exported ONNX input, in float64.

    For a hull exported with ``input_form='box'``: ``λ`` = the spacings of the sorted
    ``u`` (``(…, n)``); with ``'simplex'``, and for a parallelotope, ``λ = x``; for a box,
    the image ``x`` reshaped to ``(…, *S)``. Feed the result to ``input_set.image(…,
    dtype=torch.float64)`` to get the exact image in float64.
    """
    _checks.choice(input_form, "input_form", INPUT_FORMS)
    x = torch.as_tensor(np.asarray(x), dtype=torch.float64)
    if isinstance(input_set, Box):
        return x.reshape(*x.shape[:-1], *input_set.shape)
    if _form(input_set, input_form) == "box" and not isinstance(input_set, Parallelotope):
        return lambda_of_box(x)
    return x


def export_onnx(model: nn.Module, example: torch.Tensor, path, *, opset=17) -> Path:
    """Write ``model`` (a float32 eval-mode copy) as ONNX with input ``x`` and output ``y``.

    ``example`` fixes the input shape, batch included (every value's shape is static),
    e.g. ``torch.zeros(1, 3, 64, 64)`` for the CNN backbone or its proxy; batch norms are
    folded as for :func:`export_instance`. The file appears only when the export
    succeeded.

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
        ``Y_neg ≥ Y_pos``, ``neg = None`` standing for the constant 0 (the compact form's
        ``Y_pos ≤ 0``; the violation is any one of them); ``n_inputs``, ``n_outputs``.

    Raises
    ------
    ValueError
        On a line outside the subset.
    """
    decl = re.compile(r"\(declare-const ([XY])_(\d+) Real\)")
    bound = re.compile(r"\(assert \((<=|>=) X_(\d+) (\S+)\)\)")
    linear = re.compile(r"\(assert \(<= \(\+((?: X_\d+)+)\) (\S+)\)\)")
    clause = re.compile(r"\(and \(>= Y_(\d+) Y_(\d+)\)\)")
    compact = re.compile(r"\(and \(<= Y_(\d+) 0\.0\)\)")
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
        elif m := compact.fullmatch(line):
            disjuncts.append((None, int(m[1])))
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


def _vnnlib_text(
    input_set, spec: ArgmaxSpec, name: str, form: str, dtype: str, version, margins
) -> str:
    """The VNN-LIB text; ``margins``: the graph's :class:`WorstMargins` (compact form) or
    None (full form)."""
    n = input_set.n
    m = spec.n_outputs if margins is None else len(margins.groups)
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
        f"; model outputs: {spec.n_outputs} in {spec.n_groups} groups {spec.group_sizes}, "
        f"targets {spec.targets}",
    ]
    if margins is None:
        header += [
            f"; outputs: model.onnx 'y' (1, {m}), the model's outputs",
            f"; {spec.n_rows} margin rows, one disjunct Y_j >= Y_t each; the assertions "
            "state a violation (unsat = verified), a tie included",
        ]
        rows = list(zip(spec.row_neg.tolist(), spec.row_pos.tolist()))
    else:
        header += [
            f"; outputs: model.onnx 'y' (1, {m}), Y_i = the worst margin of the i-th of "
            f"groups {margins.groups}: min of y_t - y_j over its model outputs j other "
            "than its target t",
            "; one disjunct Y_i <= 0 per group; the assertions state a violation "
            "(unsat = verified), a tie (Y_i = 0) included",
        ]
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
    if margins is None:
        violations = [f"(>= {y[j]} {y[t]})" for j, t in rows]
    else:
        violations = [f"(<= {v} 0.0)" for v in y]
    clause = "  (and {})" if version == "1.0" else "  {}"  # 1.0: a disjunct is a conjunction
    clauses = [clause.format(v) for v in violations]
    for v, lo, hi in zip(x, lower, upper):
        lines += [f"(assert (>= {v} {_number(lo)}))", f"(assert (<= {v} {_number(hi)}))"]
    if simplex:
        lines.append(f"(assert (<= (+ {' '.join(x)}) 1.0))")
    lines += ["", "(assert (or", *clauses, "))"]
    return "\n".join(lines) + "\n"


def _export_onnx(wrapper: nn.Module, example, name: str, path: str, opset: int) -> None:
    """Export ``wrapper`` for the input ``example`` (its shape fixed, batch included): its
    batch norms folded in place (:func:`_fold_batch_norms`; callers pass their own copy),
    the TorchScript exporter first (needs no onnxscript), then the torch.export one; then
    :func:`_finish_graph`."""
    wrapper = _fold_batch_norms(wrapper)
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
            _finish_graph(path)
            return
        except Exception as exc:
            errors.append(f"{'dynamo' if dynamo else 'torchscript'} exporter: {exc}")
    raise ValueError("model: failed to export to ONNX (" + "; ".join(errors) + ")")


class _ChannelAffine(nn.Module):
    """An eval-mode batch norm as ``x * scale + shift`` per channel (dim 1 of ``(B, C, …)``):
    ``Mul`` and ``Add`` in ONNX."""

    def __init__(self, bn: _BatchNorm) -> None:
        super().__init__()
        scale = torch.rsqrt(bn.running_var + bn.eps)
        if bn.weight is not None:
            scale = scale * bn.weight.detach()
        shift = -bn.running_mean * scale
        if bn.bias is not None:
            shift = shift + bn.bias.detach()
        self.register_buffer("scale", scale)
        self.register_buffer("shift", shift)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = (-1,) + (1,) * (x.ndim - 2)
        return x * self.scale.reshape(shape) + self.shift.reshape(shape)


def _fold_batch_norms(module: nn.Module) -> nn.Module:
    """``module`` without batch norms (changed in place; returned, as a lone batch norm is
    replaced): one that follows a (transposed) convolution in an ``nn.Sequential`` folded
    into it (:func:`torch.nn.utils.fusion.fuse_conv_bn_eval`), any other a
    :class:`_ChannelAffine`.

    ONNX's ``BatchNormalization`` has carried ``training_mode`` since opset 14, which
    onnx2pytorch (alpha-beta-CROWN's and NeuralSAT's importer) refuses; the TorchScript
    exporter folds a batch norm into a ``Conv`` but not into a ``ConvTranspose``.
    """
    for seq in [m for m in module.modules() if isinstance(m, nn.Sequential)]:
        for i in range(1, len(seq)):
            conv, bn = seq[i - 1], seq[i]
            transpose = isinstance(conv, _ConvTransposeNd)
            # torch folds a transposed convolution's output channels for one group only
            if (
                isinstance(conv, _ConvNd)
                and isinstance(bn, _BatchNorm)
                and not (transpose and conv.groups > 1)
            ):
                seq[i - 1] = fuse_conv_bn_eval(conv, bn, transpose=transpose)
                seq[i] = nn.Identity()
    if isinstance(module, _BatchNorm):
        return _ChannelAffine(module)
    for name, child in list(module.named_modules()):
        if isinstance(child, _BatchNorm):
            parent, _, attr = name.rpartition(".")
            setattr(module.get_submodule(parent), attr, _ChannelAffine(child))
    return module


def _finish_graph(path: str) -> None:
    """Fold constants, replace zero padding by convolutions and fix every value's shape in
    the ONNX file ``path``, in place.

    A node that depends only on constants becomes an initializer: the TorchScript exporter
    leaves ``F.pad``'s pads as a Constant/Slice/Concat/Transpose chain (its reversing
    Slice stops torch's own folding). Strict shape inference then gives every value and
    the output their static shapes (the exporter leaves symbolic ones, ``Flatteny_dim_0``,
    behind that chain); each ``Pad`` that adds zeros to the last two axes of a 4-d tensor
    becomes a depthwise ``Conv`` (:func:`_pad_as_conv`), and the full checker must pass.
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
    graph.ClearField("value_info")
    model = onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True)
    graph = model.graph
    types = {v.name: v.type.tensor_type for v in [*graph.input, *graph.value_info]}
    names = {t.name for t in graph.initializer} | {x for n in graph.node for x in n.output}
    nodes = []
    for node in graph.node:
        conv = node.op_type == "Pad" and _pad_as_conv(node, values, types.get(node.input[0]), names)
        if not conv:
            nodes.append(node)
            continue
        nodes.append(conv[0])
        graph.initializer.append(conv[1])
        names.add(conv[1].name)
    graph.ClearField("node")
    graph.node.extend(nodes)
    used = {x for node in nodes for x in node.input} | {o.name for o in graph.output}
    kept = [t for t in graph.initializer if t.name in used]
    graph.ClearField("initializer")
    graph.initializer.extend(kept)
    graph.ClearField("value_info")
    model = onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True)
    for value in [*model.graph.input, *model.graph.output, *model.graph.value_info]:
        dims = value.type.tensor_type.shape.dim
        if not all(d.HasField("dim_value") for d in dims):
            raise ValueError(f"model: the ONNX value {value.name!r} has no static shape")
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, path)


def _pad_as_conv(node, constants: dict, input_type, names: set):
    """``(conv, weight)``: a ``Conv`` node and its weight initializer that compute the
    ``Pad`` ``node`` exactly, or None where ``node`` is not a ``Pad`` that adds zeros
    (``mode`` constant, value 0 or none, pads ``>= 0`` and constant) to the last two axes
    of a float tensor of static shape ``(N, C, H, W)``.

    Zeros ``t, b`` before and after the rows and ``l, r`` before and after the columns:
    a depthwise ``Conv`` (``group = C``, stride 1) with symmetric ``pads`` ``P = max(t, b)``
    and ``Q = max(l, r)`` and a ``(1 + |t − b|) × (1 + |l − r|)`` kernel whose single one
    sits at ``(P − t, Q − l)``, all else zero: its output ``(N, C, H + t + b, W + l + r)``
    is the padded tensor, each entry one input times 1 plus zeros. NeuralSAT 0.2.17's
    auto_LiRPA cannot bound a ``Pad`` (``BoundPad.forward() missing 1 required
    positional argument: 'pad'``), and the onnx2pytorch of NeuralSAT and α,β-CROWN
    converts a ``Conv``'s or an ``AveragePool``'s asymmetric ``pads`` into a
    ``ConstantPad2d`` with rows and columns swapped; zeros concatenated as constants would
    fix the batch size at 1, where NeuralSAT checks its import on a batch of two.
    """
    if node.op_type != "Pad" or node.domain or input_type is None:
        return None
    attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    if attrs.get("mode", b"constant") != b"constant" or len(node.input) < 2:
        return None
    ins = list(node.input) + [""] * (4 - len(node.input))
    if not all(x in constants for x in ins[1:] if x):
        return None
    dims = [d.dim_value if d.HasField("dim_value") else None for d in input_type.shape.dim]
    if len(dims) != 4 or None in dims:
        return None
    if ins[2] and np.any(constants[ins[2]] != 0):
        return None
    pads = np.asarray(constants[ins[1]], dtype=np.int64).ravel()
    axes = range(4) if not ins[3] else [int(a) % 4 for a in np.ravel(constants[ins[3]])]
    full = np.zeros(8, dtype=np.int64)
    for i, axis in enumerate(axes):
        full[axis], full[axis + 4] = pads[i], pads[i + len(pads) // 2]
    if np.any(full < 0) or np.any(full[[0, 1, 4, 5]] != 0):
        return None
    t, l, b, r = (int(v) for v in full[[2, 3, 6, 7]])
    dtype = onnx.helper.tensor_dtype_to_np_dtype(input_type.elem_type)
    if not np.issubdtype(dtype, np.floating):
        return None
    channels, p, q = dims[1], max(t, b), max(l, r)
    kernel = np.zeros((channels, 1, 1 + abs(t - b), 1 + abs(l - r)), dtype=dtype)
    kernel[:, :, p - t, q - l] = 1
    name, k = f"{node.output[0]}.kernel", 0
    while name in names:
        k += 1
        name = f"{node.output[0]}.kernel{k}"
    conv = onnx.helper.make_node(
        "Conv",
        [ins[0], name],
        list(node.output),
        name=node.name or node.output[0],
        group=channels,
        kernel_shape=list(kernel.shape[2:]),
        pads=[p, q, p, q],
        strides=[1, 1],
    )
    return conv, numpy_helper.from_array(kernel, name)


#: A verifier's counterexample may leave a float64 worst margin above 0 by this much, times
#: ``1 + max |y(X0)|``: the verifiers check their points in float32.
COUNTEREXAMPLE_TOLERANCE = 1e-5


def read_answer(path) -> tuple[str, np.ndarray | None]:
    """A VNN-COMP verifier's result file (NeuralSAT's ``--result_file``, α,β-CROWN's
    ``--results_file``): its answer, the first line (``sat``, ``unsat``, ``timeout``, …;
    ``''`` for an empty file), and the input of a counterexample that follows it, the
    ``(X_i value)`` pairs as an ndarray in index order (None where there are none)."""
    status, *lines = Path(path).read_text().splitlines() or [""]
    pairs = re.findall(r"\(X_(\d+)\s+([^\s)]+)\)", "\n".join(lines))
    values = {int(k): float(v) for k, v in pairs}
    return status.strip(), (np.array([values[k] for k in sorted(values)]) if values else None)


def check_counterexample(model, hull, spec, x, input_form: str = "box") -> dict:
    """The float64 re-check of a verifier's counterexample ``x`` (an assignment of an
    exported instance's ONNX input, :func:`kpstudy.verify.export.point_of_input`'s
    ``input_form``) on the torch ``model`` (the proxy) over the ``hull`` with ``spec``:
    ``inside`` (its λ lies in the hull, to 1e-6), ``margin`` (the float64 worst margin at
    its image), ``scale`` (``1 + max |y(X0)|``) and ``violates`` (``margin`` ≤
    :data:`COUNTEREXAMPLE_TOLERANCE` × ``scale``); a real counterexample is ``inside`` and
    ``violates``."""
    lam = point_of_input(hull, np.asarray(x)[None], input_form)
    double = copy.deepcopy(model).double()
    with torch.no_grad():
        scale = 1 + double(hull.vertices[:1].double()).abs().max().item()
        margin = spec.margins(double(hull.image(lam, dtype=torch.float64))).min().item()
    return {
        "inside": bool(hull.contains_lambda(lam, tol=1e-6).all()),
        "margin": margin,
        "scale": scale,
        "violates": margin <= COUNTEREXAMPLE_TOLERANCE * scale,
    }
