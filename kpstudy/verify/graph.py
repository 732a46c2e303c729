"""Trace a torch model into a graph of supported operators (torch.fx).

Supported: ``Conv2d``, ``ConvTranspose2d``, ``BatchNorm2d`` (eval), ``ReLU``,
``AvgPool2d``, the cell pool :func:`kpstudy.verify.ops.cell_pool` (which the proxy's
:class:`~kpstudy.models.pooling.CellAvgPool2d` calls), ``MaxPool2d``, ``Linear``,
``Flatten``/``flatten``, residual ``+``, ``torch.cat``, slicing that keeps the batch
dimension, ``Identity`` and ``Dropout`` (eval); more modules through :data:`MODULES`
(see :mod:`kpstudy.verify.operators`, "Adding a layer"). Anything else is refused with an
error naming the operation and the node. A batch norm that alone follows a convolution
is folded into it (one node, named ``conv+bn``), a chain of transposed convolutions
whose kernels equal their strides is fused into one where that saves multiply-adds
(:class:`~kpstudy.verify.ops.PatchConvTranspose`), and such a layer with a per-channel
filter that alone reads it (:class:`~kpstudy.verify.ops.FilteredPatchConvTranspose`),
unless the graph is traced ``differentiable``: then every operator keeps the model's own
modules and the affine offsets are computed from them at each use, so bounds carry
gradients to every parameter (certified training, :mod:`kpstudy.models.certified`).
"""

from __future__ import annotations

import copy
import functools
import operator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import fx, nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from kpstudy.verify import operators, ops

#: Module type → its graph operator (the module is not traced into).
MODULES = {
    nn.Conv2d: ops.Conv,
    nn.ConvTranspose2d: ops.ConvTranspose,
    nn.Linear: ops.Dense,
    nn.BatchNorm2d: ops.BatchNorm,
    nn.AvgPool2d: ops.Pool,
    nn.MaxPool2d: ops.MaxPool,
    nn.ReLU: lambda m: ops.ReLU(),
    nn.Flatten: lambda m: ops.Flatten(m.start_dim, m.end_dim),
    nn.Identity: lambda m: ops.Identity(),
    nn.Dropout: lambda m: _eval_identity(m),
}


def _eval_identity(m: nn.Module) -> ops.Identity:
    if m.training:
        raise ValueError("model: Dropout needs eval mode (call model.eval())")
    return ops.Identity()


class _Tracer(fx.Tracer):
    def __init__(self) -> None:
        super().__init__(autowrap_functions=(ops.cell_pool,))  # one node, not traced into

    def is_leaf_module(self, m: nn.Module, qualname: str) -> bool:
        return type(m) in MODULES or super().is_leaf_module(m, qualname)


@dataclass
class Node:
    """One graph value: the operator that makes it from ``inputs`` (indices of earlier
    nodes; node 0 is the model input, ``op=None``) and its shape without the batch."""

    name: str
    op: ops.Op | None
    inputs: tuple[int, ...]
    shape: tuple[int, ...]
    offset: torch.Tensor | None = None  # ``forward(0)`` of an affine op, (1, *shape)


class Graph:
    """A traced model: :attr:`nodes` in topological order, the last one the output."""

    def __init__(self, nodes: list[Node], dtype: torch.dtype, differentiable: bool = False) -> None:
        self.nodes = nodes
        self.dtype = dtype
        self.differentiable = differentiable
        self.consumers = [[] for _ in nodes]
        for i, node in enumerate(nodes):
            for j in node.inputs:
                self.consumers[j].append(i)

    @property
    def output_size(self) -> int:
        n = 1
        for s in self.nodes[-1].shape:
            n *= s
        return n

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Concrete evaluation ``(B, *S) → (B, *out)`` through the traced operators."""
        values = [x]
        for node in self.nodes[1:]:
            values.append(node.op.forward(*(values[j] for j in node.inputs)))
        return values[-1]

    def split_affine_tail(self) -> tuple[Graph, Graph] | None:
        """The graph as a head up to its last non-affine node and the affine tail from
        there to the output (node 0 of the tail stands for the head's output); None when
        the output is not an affine map of one such node (or nothing precedes it).

        A zonotope maps exactly through the tail, so a caller can bound its output from
        the head's value cheaply first (the symbols moved into the radius) and pay for
        the symbols through the tail only where that is not enough
        (:func:`kpstudy.verify.reachable.reachable_argmax`)."""
        last = len(self.nodes)
        k = None
        for start in range(last - 1, 1, -1):
            node = self.nodes[start]
            if node.op.kind != "affine":
                break
            tail = self.nodes[start:]
            if min(j for n in tail for j in n.inputs) >= start - 1:
                k = start
        if k is None:
            return None
        head = Graph(self.nodes[:k], self.dtype, self.differentiable)
        anchor = Node("tail input", None, (), self.nodes[k - 1].shape)
        tail = [
            Node(n.name, n.op, tuple(j - (k - 1) for j in n.inputs), n.shape, n.offset)
            for n in self.nodes[k:]
        ]
        return head, Graph([anchor, *tail], self.dtype, self.differentiable)

    def output_channels(self, channels: torch.Tensor) -> Graph | None:
        """The graph with its output node computing only channels ``channels`` (indices
        of a ``(C, H, W)`` output), or None where that node is not a convolution or
        transposed convolution of one group (:meth:`kpstudy.verify.ops.Op.output_channels`)."""
        last = self.nodes[-1]
        op = last.op.output_channels(channels) if len(last.shape) == 3 else None
        if op is None:
            return None
        i = len(self.nodes) - 1
        shape = (len(channels), *last.shape[1:])
        node = Node(last.name, op, last.inputs, shape, self.offset(i)[:, channels].detach())
        return Graph([*self.nodes[:-1], node], self.dtype)

    def offset(self, i: int) -> torch.Tensor:
        """``forward(0)`` of affine node ``i``, ``(1, *shape)``: stored, or computed from the
        live modules (with their gradients) in a differentiable graph."""
        node = self.nodes[i]
        if node.offset is not None:
            return node.offset
        zeros = [torch.zeros(1, *self.nodes[j].shape, dtype=self.dtype) for j in node.inputs]
        return node.op.forward(*zeros)


def trace(model: nn.Module, example: torch.Tensor, *, differentiable: bool = False) -> Graph:
    """The graph of ``model`` for inputs shaped like ``example (1, *S)``.

    With ``differentiable``, batch norms stay separate nodes and no offset is stored
    (:meth:`Graph.offset` computes them): bounds then have gradients with respect to the
    model's parameters. The model's batch norms must be in eval mode whenever the graph is
    used.

    Raises
    ------
    ValueError
        ``model: unsupported operation …`` naming the operation and node, or a
        BatchNorm in training mode.
    """
    if not isinstance(model, nn.Module):
        raise ValueError(f"model: expected a torch.nn.Module, got {type(model).__name__}")
    try:
        gm = fx.GraphModule(model, _Tracer().trace(model))
    except Exception as exc:  # data-dependent control flow, unsupported Python
        raise ValueError(f"model: could not be traced with torch.fx ({exc})") from exc
    modules = dict(gm.named_modules())
    constants: dict[str, torch.Tensor] = {}  # get_attr nodes: buffers read in a forward
    index: dict[str, int] = {}
    nodes: list[Node] = []
    dtype = next((p.dtype for p in model.parameters()), example.dtype)
    for n in gm.graph.nodes:
        if n.op == "placeholder":
            if nodes:
                raise ValueError("model: expected a single input tensor")
            index[n.name] = 0
            nodes.append(Node(n.name, None, (), tuple(example.shape[1:])))
            continue
        if n.op == "get_attr":
            constants[n.name] = functools.reduce(getattr, n.target.split("."), gm)
            continue
        if n.op == "output":
            if not isinstance(n.args[0], fx.Node):
                raise ValueError("model: expected a single output tensor")
            output = index[n.args[0].name]
            continue
        op, args = _operator(n, modules, constants)
        if op.kind not in operators.RULES:
            kind = f"operator kind {op.kind!r}"
            raise ValueError(f"model: {kind} has no bound rules (node {n.name!r})")
        ins = tuple(index[a.name] for a in args)
        index[n.name] = len(nodes)
        nodes.append(Node(n.name, op, ins, ()))
    if output != len(nodes) - 1:
        raise ValueError("model: the output must be the last operation")
    if not differentiable:
        nodes = _fuse_patch_filters(_fuse_patch_chains(_fold_batch_norms(nodes)))
    try:
        _infer_shapes(nodes, example.to(dtype), offsets=not differentiable)
    except RuntimeError as exc:  # e.g. channels or sizes that do not fit the first layer
        raise ValueError(
            f"input_set: images of shape {tuple(example.shape[1:])} do not fit the model ({exc})"
        ) from exc
    return Graph(nodes, dtype, differentiable)


def _operator(n: fx.Node, modules: dict, constants: dict) -> tuple[ops.Op, list[fx.Node]]:
    """The :mod:`ops` operator of an fx node, and the fx nodes it reads (``constants``:
    the tensors of get_attr nodes)."""
    where = f"(node {n.name!r})"
    if n.op == "call_module":
        m = modules[n.target]
        make = MODULES.get(type(m))
        if make is None:
            raise ValueError(f"model: unsupported operation {type(m).__name__} {where}")
        return make(m), _tensor_args(n, 1, where)
    if n.op == "call_function":
        f = n.target
        if f in (operator.add, torch.add):
            if n.kwargs or len(n.args) != 2:
                raise ValueError(f"model: only x + y of two tensors is supported {where}")
            return ops.Add(), _tensor_args(n, 2, where)
        if f in (torch.relu, F.relu):
            return ops.ReLU(), _tensor_args(n, 1, where, n.args[:1])
        if f in (torch.cat, torch.concat):
            xs = list(n.args[0])
            dim = n.args[1] if len(n.args) > 1 else n.kwargs.get("dim", 0)
            return ops.Cat(len(xs), dim), _tensor_args(n, len(xs), where, xs)
        if f is torch.flatten:
            start = n.args[1] if len(n.args) > 1 else n.kwargs.get("start_dim", 0)
            end = n.args[2] if len(n.args) > 2 else n.kwargs.get("end_dim", -1)
            return ops.Flatten(start, end), _tensor_args(n, 1, where, n.args[:1])
        if f is ops.cell_pool:
            x, pad, kernel_size, scale = n.args
            if n.kwargs or not isinstance(scale, fx.Node) or scale.name not in constants:
                raise ValueError(f"model: cell_pool(x, pad, kernel_size, buffer) expected {where}")
            return ops.CellPool(pad, kernel_size, constants[scale.name]), _tensor_args(
                n, 1, where, [x]
            )
        if f is operator.getitem:
            idx = n.args[1] if isinstance(n.args[1], tuple) else (n.args[1],)
            if not idx or idx[0] != slice(None) or any(isinstance(i, fx.Node) for i in idx):
                raise ValueError(f"model: only slicing that keeps the batch is supported {where}")
            return ops.Slice(idx), _tensor_args(n, 1, where, n.args[:1])
        name = getattr(f, "__name__", str(f))
        raise ValueError(f"model: unsupported operation {name} {where}")
    if n.op == "call_method":
        if n.target == "flatten":
            start = n.args[1] if len(n.args) > 1 else n.kwargs.get("start_dim", 0)
            end = n.args[2] if len(n.args) > 2 else n.kwargs.get("end_dim", -1)
            return ops.Flatten(start, end), _tensor_args(n, 1, where, n.args[:1])
        if n.target == "relu":
            return ops.ReLU(), _tensor_args(n, 1, where, n.args[:1])
        raise ValueError(f"model: unsupported operation Tensor.{n.target} {where}")
    raise ValueError(f"model: unsupported operation {n.op} {n.target} {where}")


def _merge_pairs(nodes: list[Node], merge) -> list[Node]:
    """``nodes`` with each node that alone reads the node before it (which nothing else
    reads) replaced, together with that node, by ``merge(before.op, node.op)`` wherever
    that gives an operator (one node named ``before+node``; None keeps both)."""
    uses = [0] * len(nodes)
    for node in nodes:
        for j in node.inputs:
            uses[j] += 1
    out: list[Node] = []
    where: dict[int, int] = {}  # old index → new index
    for i, node in enumerate(nodes):
        inputs = tuple(where[j] for j in node.inputs)
        if out and inputs == (len(out) - 1,) and uses[node.inputs[0]] == 1:
            prev = out[-1]
            op = merge(prev.op, node.op)
            if op is not None:
                out[-1] = Node(f"{prev.name}+{node.name}", op, prev.inputs, ())
                where[i] = len(out) - 1
                continue
        where[i] = len(out)
        out.append(Node(node.name, node.op, inputs, node.shape))
    return out


def _fold_batch_norms(nodes: list[Node]) -> list[Node]:
    """Fold each eval batch norm into the (transposed) convolution that alone feeds it:
    one affine node instead of two, the same map up to float rounding (every bound method
    then makes one pass fewer per convolution)."""

    def fold(first, second):
        conv = isinstance(first, (ops.Conv, ops.ConvTranspose)) and not first.m.training
        if not (conv and isinstance(second, ops.BatchNorm)):
            return None
        transpose = isinstance(first, ops.ConvTranspose)
        return type(first)(fuse_conv_bn_eval(first.m, second.m, transpose=transpose))

    return _merge_pairs(nodes, fold)


def _patch_stride(op) -> int | None:
    """The stride ``s`` of a transposed convolution that maps each input position to its own
    ``s × s`` output patch (kernel = stride, no padding, no dilation, one group), else None."""
    if not isinstance(op, ops.ConvTranspose) or op.m.training:
        return None
    m = op.m
    k, s = m.kernel_size, m.stride
    plain = m.padding == (0, 0) and m.output_padding == (0, 0) and m.dilation == (1, 1)
    if k[0] != k[1] or k != s or not plain or m.groups != 1:
        return None
    return k[0]


def _fuse_patch_chains(nodes: list[Node]) -> list[Node]:
    """Fuse consecutive patch-local transposed convolutions (:func:`_patch_stride`; each
    consumed by the next alone) into one :class:`~kpstudy.verify.ops.PatchConvTranspose`
    wherever its multiply-adds per input position are no more than the pair's: the same
    affine map, computed in float64. A zonotope pays a layer's multiply-adds once per error
    symbol, so the verification-friendly CNN's five decoder layers (128 → 23 channels,
    4×4 patches) cost a third as one."""

    def fuse(first, second):
        if not (_patch_stride(first) and _patch_stride(second)):
            return None
        (c_in, _, s, _), (_, c_out, t, _) = first.m.weight.shape, second.m.weight.shape
        if c_in * c_out * (s * t) ** 2 > _patch_cost(first) + _patch_cost(second) * s * s:
            return None
        return _compose(first, second)

    return _merge_pairs(nodes, fuse)


def _fuse_patch_filters(nodes: list[Node]) -> list[Node]:
    """Fuse a patch-local transposed convolution and the per-channel ``k × k`` filter that
    alone reads it (stride 1, one filter per channel, padding below ``k``) into one
    :class:`~kpstudy.verify.ops.FilteredPatchConvTranspose`. It has more multiply-adds
    (``(s + k − 1)²`` per pair of channels against ``s²``, plus the filter's ``k²`` per
    output), but a depthwise convolution runs at a fraction of a dense one's speed on CPU:
    on the zonotope's symbol blocks of the verification-friendly CNN (128 → 23 channels,
    4×4 patches, a 3×3 filter) the fused layer takes about 2.5× less time than the pair."""

    def fuse(first, second):
        if not _patch_stride(first) or not isinstance(second, ops.Conv) or second.m.training:
            return None
        m = second.m
        c = first.m.weight.shape[1]
        k, p = m.kernel_size, m.padding
        square = k[0] == k[1] and isinstance(p, tuple) and p[0] == p[1] < k[0]
        plain = m.stride == (1, 1) and m.dilation == (1, 1)
        depthwise = m.groups == c == m.in_channels == m.out_channels
        if not (square and plain and depthwise):
            return None
        return ops.FilteredPatchConvTranspose(first, second)

    return _merge_pairs(nodes, fuse)


def _patch_cost(op) -> int:
    """Multiply-adds per input position of a patch-local transposed convolution."""
    c_in, c_out, kh, kw = op.m.weight.shape
    return c_in * c_out * kh * kw


def _compose(first, second) -> ops.PatchConvTranspose:
    """``second ∘ first`` of two patch-local transposed convolutions, as one: its weight is
    the chain's linear part on each one-hot input pixel, its patch bias the chain at zero."""
    c_in = first.m.weight.shape[0]
    with torch.no_grad():
        dtype = first.m.weight.dtype
        one = [_float64(op) for op in (first, second)]
        eye = torch.eye(c_in, dtype=torch.float64).reshape(c_in, c_in, 1, 1)
        weight = one[1].linear(one[0].linear(eye))  # (C_in, C_out, s, s)
        bias = one[1].forward(one[0].forward(torch.zeros(1, c_in, 1, 1, dtype=torch.float64)))
    return ops.PatchConvTranspose(weight.to(dtype), bias[0].to(dtype))


def _float64(op: ops.ConvTranspose) -> ops.ConvTranspose:
    """A float64 copy of a (patch) transposed convolution."""
    if isinstance(op, ops.PatchConvTranspose):
        return ops.PatchConvTranspose(op.m.weight.double(), op.bias.double())
    return ops.ConvTranspose(copy.deepcopy(op.m).double())


def _tensor_args(n: fx.Node, count: int, where: str, args=None) -> list[fx.Node]:
    args = list(n.args if args is None else args)
    if len(args) != count or not all(isinstance(a, fx.Node) for a in args):
        raise ValueError(f"model: expected {count} tensor argument(s) {where}")
    return args


def _infer_shapes(nodes: list[Node], example: torch.Tensor, offsets: bool = True) -> None:
    """Fill in output shapes and (with ``offsets``) affine offsets; refuse ops that would
    mix the batch."""
    values = [example]
    with torch.no_grad():
        for node in nodes[1:]:
            xs = [values[j] for j in node.inputs]
            op = node.op
            if isinstance(op, (ops.Flatten, ops.Cat)):
                dim = op.start_dim if isinstance(op, ops.Flatten) else op.dim
                if dim % xs[0].ndim == 0:
                    raise ValueError(
                        f"model: {type(op).__name__.lower()} over the batch dimension "
                        f"(node {node.name!r})"
                    )
            y = op.forward(*xs)
            node.shape = tuple(y.shape[1:])
            if offsets and isinstance(operators.rules(op.kind), operators.AffineRules):
                node.offset = op.forward(*(torch.zeros_like(x) for x in xs))
            values.append(y)
