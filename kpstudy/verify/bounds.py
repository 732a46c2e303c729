"""Sound bounds of a traced network over an input set, in the set's few parameters.

A batch of ``B`` regions (branch-and-bound nodes) enters as affine inputs
``x = c + Σ_i θ_i G_i`` with ``θ`` in a *domain* — the standard simplex
``{θ ≥ 0, Σ θ ≤ 1}`` for a convex hull, the unit cube for a parallelotope — or, for a
box, as an interval (no ``θ``). Every value of the network is then bounded by two affine
functions of ``θ``, stored as coefficient stacks ``(B, q, *shape)`` (row 0 the constant,
rows 1… the ``θ`` coefficients) in centre/radius form: lower ``mid − rad``, upper
``mid + rad``. The minimum of ``a0 + a·θ`` is exact: ``a0 + min(0, min_i a_i)`` over the
simplex, ``a0 + Σ_i min(0, a_i)`` over the cube.

Methods
-------
``'ibp'``
    Interval bounds: the input region's box pushed through (``q = 1``).
``'forward'``
    Linear bounds in ``θ`` carried forward (affine layers exactly, ReLU by its
    triangle relaxation, max pooling by its largest-lower-bound input); margins from
    the output's coefficient stacks, so ``y[t] − y[j]`` keeps its dependence on ``θ``.
``'crown'``
    Backward linear relaxation of each margin row (CROWN) through the whole network,
    with pre-activation bounds from ``'forward'``, concretised exactly over the domain;
    the result is the element-wise maximum with ``'forward'``. Rows go in chunks, so no
    ``(rows × activation size)`` tensor larger than ``memory`` elements is formed.

Floating point: bounds are computed in the graph's dtype; the verifier asks for a
margin above a tolerance or recomputes a node in float64 before it says ``holds``.
"""

from __future__ import annotations

import math

import torch

from kpstudy.verify import ops
from kpstudy.verify.graph import Graph, trace

METHODS = ("ibp", "forward", "crown")


def domain_min(a: torch.Tensor, domain: str) -> torch.Tensor:
    """Exact minimum over ``θ`` of ``a[:, 0] + Σ_i a[:, i] θ_i`` for ``a (B, q, …)``."""
    if a.shape[1] == 1 or domain == "point":
        return a[:, 0]
    rest = a[:, 1:]
    if domain == "simplex":
        return a[:, 0] + rest.min(1).values.clamp_max(0.0)
    if domain == "cube":
        return a[:, 0] + rest.clamp_max(0.0).sum(1)
    raise ValueError(f"domain: expected 'simplex', 'cube' or 'point', got {domain!r}")


class Region:
    """``B`` input regions: coefficient stacks ``mid``, ``rad`` ``(B, q, *S)`` and a domain."""

    def __init__(self, mid: torch.Tensor, rad: torch.Tensor, domain: str) -> None:
        self.mid, self.rad, self.domain = mid, rad, domain

    @classmethod
    def affine(cls, coeff: torch.Tensor, domain: str) -> Region:
        """Exact affine inputs ``coeff (B, q, *S)`` over ``domain``."""
        return cls(coeff, torch.zeros_like(coeff), domain)

    @classmethod
    def interval(cls, lower: torch.Tensor, upper: torch.Tensor) -> Region:
        """Boxes ``lower, upper (B, *S)``."""
        return cls(((lower + upper) / 2)[:, None], ((upper - lower) / 2)[:, None], "point")

    def to_interval(self) -> Region:
        low = domain_min(self.mid - self.rad, self.domain)
        high = -domain_min(-(self.mid + self.rad), self.domain)
        return Region.interval(low, high)

    @property
    def batch(self) -> int:
        return self.mid.shape[0]


class _State:
    """Per-node pre-activation data kept for the backward pass."""

    def __init__(self) -> None:
        self.relu: dict[int, tuple] = {}  # node → (lower slope, upper slope, upper offset)
        self.maxpool: dict[int, tuple] = {}  # node → (argmax index, decided, upper const)


def propagate(graph: Graph, region: Region) -> tuple[Region, _State]:
    """Forward coefficient bounds of the output for ``B`` regions, and what CROWN needs."""
    values: list[tuple | None] = [(region.mid, region.rad)] + [None] * (len(graph.nodes) - 1)
    remaining = [len(c) for c in graph.consumers]
    state = _State()
    B, q = region.mid.shape[:2]
    for i, node in enumerate(graph.nodes[1:], start=1):
        ins = [values[j] for j in node.inputs]
        op = node.op
        if op.kind == "affine":
            mid = _apply(op.linear, [m for m, _ in ins], B, q)
            rad = _apply(op.abs_linear, [r for _, r in ins], B, q)
            mid[:, 0] += node.offset[0]
            values[i] = (mid, rad)
        elif op.kind == "relu":
            values[i] = _relu(i, *ins[0], region.domain, state)
        else:
            values[i] = _maxpool(i, op, *ins[0], region.domain, state)
        for j in node.inputs:
            remaining[j] -= 1
            if remaining[j] == 0 and j > 0:
                values[j] = None
    mid, rad = values[-1]
    return Region(mid, rad, region.domain), state


def _apply(f, xs: list[torch.Tensor], B: int, q: int) -> torch.Tensor:
    y = f(*(x.reshape(B * q, *x.shape[2:]) for x in xs))
    return y.reshape(B, q, *y.shape[1:])


def _relu(i, mid, rad, domain, state):
    low, up = mid - rad, mid + rad
    l = domain_min(low, domain)
    u = -domain_min(-up, domain)
    active, dead = l >= 0, u <= 0
    unstable = ~(active | dead)
    s = torch.where(unstable, u / (u - l).clamp_min(1e-30), active.to(mid.dtype))
    alpha = torch.where(unstable, (u > -l).to(mid.dtype), active.to(mid.dtype))
    offset = torch.where(unstable, -s * l, torch.zeros_like(l))  # upper: s·z − s·l
    state.relu[i] = (alpha, s, offset)
    new_low, new_up = alpha[:, None] * low, s[:, None] * up
    new_up[:, 0] += offset
    return (new_up + new_low) / 2, (new_up - new_low) / 2


def _maxpool(i, op: ops.MaxPool, mid, rad, domain, state):
    B, q, C, H, W = mid.shape
    low, up = mid - rad, mid + rad
    l = domain_min(low, domain)
    u = -domain_min(-up, domain)
    lw, uw = op.windows(l, float("-inf")), op.windows(u, float("-inf"))  # (B, C, k, L)
    best = lw.argmax(2, keepdim=True)
    l_best = lw.gather(2, best)
    others = uw.scatter(2, best, float("-inf")).amax(2, keepdim=True)
    decided = (l_best >= others)[:, :, 0]  # (B, C, L)
    u_max = uw.amax(2)
    Ho, Wo = op.out_size(H, W)
    pick = lambda x: (  # noqa: E731
        op.windows(x.reshape(B * q, C, H, W), 0.0)
        .reshape(B, q, C, -1, Ho * Wo)
        .gather(3, best[:, None].expand(B, q, C, 1, Ho * Wo))[:, :, :, 0]
    )
    new_low = pick(low)
    new_up = torch.where(decided[:, None], pick(up), torch.zeros_like(new_low))
    new_up[:, 0] += torch.where(decided, torch.zeros_like(u_max), u_max)
    state.maxpool[i] = (best[:, :, 0], decided, torch.where(decided, 0.0, u_max), (H, W))
    shape = (B, q, C, Ho, Wo)
    return ((new_up + new_low) / 2).reshape(shape), ((new_up - new_low) / 2).reshape(shape)


# -- margins -------------------------------------------------------------------------------


def row_bounds(
    graph: Graph,
    region: Region,
    pos: torch.Tensor,
    neg: torch.Tensor,
    method: str = "forward",
    *,
    memory: int = 2**25,
) -> torch.Tensor:
    """Lower bounds ``(B, R)`` of ``y[pos] − y[neg]`` over each region.

    Parameters
    ----------
    graph : Graph
    region : Region
        ``B`` input regions.
    pos, neg : LongTensor, shape (R,)
        Flat output indices; ``-1`` drops a term (``neg = -1``: lower bounds of ``y[pos]``;
        ``pos = -1``: lower bounds of ``−y[neg]``).
    method : {'ibp', 'forward', 'crown'}
    memory : int
        Largest backward coefficient tensor, in elements (``'crown'`` chunks rows by it).
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "ibp":
        region = region.to_interval()
    out, state = propagate(graph, region)
    mid, rad = out.mid.flatten(2), out.rad.flatten(2)
    zero = torch.zeros((), dtype=mid.dtype)
    first = torch.where((pos >= 0)[None, None], (mid - rad)[..., pos.clamp_min(0)], zero)
    second = torch.where((neg >= 0)[None, None], (mid + rad)[..., neg.clamp_min(0)], zero)
    coeff = first - second
    lower = domain_min(coeff, out.domain)
    if method != "crown":
        return lower
    crown = torch.cat(
        [
            _backward(graph, region, state, pos[s], neg[s])
            for s in _chunks(len(pos), region, graph, memory)
        ],
        1,
    )
    return torch.maximum(lower, crown)


def _chunks(R: int, region: Region, graph: Graph, memory: int):
    biggest = max(math.prod(n.shape) for n in graph.nodes)
    step = max(1, memory // (region.batch * biggest))
    return [slice(a, min(a + step, R)) for a in range(0, R, step)]


def _backward(graph: Graph, region: Region, state: _State, pos, neg) -> torch.Tensor:
    """CROWN lower bounds ``(B, r)`` of ``y[pos] − y[neg]``: a linear lower bound of each
    row pulled back to the input, then minimised exactly over the region."""
    B, r = region.batch, len(pos)
    dtype = region.mid.dtype
    out = graph.nodes[-1]
    seed = torch.zeros(B, r, math.prod(out.shape), dtype=dtype)
    rows = torch.arange(r)
    seed[:, rows[pos >= 0], pos[pos >= 0]] = 1.0
    seed[:, rows[neg >= 0], neg[neg >= 0]] -= 1.0
    A: dict[int, torch.Tensor] = {len(graph.nodes) - 1: seed.reshape(B, r, *out.shape)}
    const = torch.zeros(B, r, dtype=dtype)
    for i in range(len(graph.nodes) - 1, 0, -1):
        a = A.pop(i, None)
        if a is None:
            continue
        node = graph.nodes[i]
        op = node.op
        if op.kind == "affine":
            const += (a * node.offset[None]).flatten(2).sum(-1)
            grads = _vjp(op.linear, [graph.nodes[j].shape for j in node.inputs], a, B * r)
        elif op.kind == "relu":
            alpha, s, offset = state.relu[i]
            a_pos, a_neg = a.clamp_min(0), a.clamp_max(0)
            const += (a_neg * offset[:, None]).flatten(2).sum(-1)
            grads = [a_pos * alpha[:, None] + a_neg * s[:, None]]
        else:
            best, decided, u_const, (H, W) = state.maxpool[i]
            grads, c = _maxpool_backward(op, a, best, decided, u_const, H, W)
            const += c
        for j, g in zip(node.inputs, grads):
            A[j] = g if j not in A else A[j] + g
    a = A.pop(0).flatten(2)  # (B, r, d)
    mid, rad = region.mid.flatten(2), region.rad.flatten(2)  # (B, q, d)
    coeff = torch.einsum("brd,bqd->brq", a, mid) - torch.einsum("brd,bqd->brq", a.abs(), rad)
    coeff[..., 0] += const
    return domain_min(coeff.transpose(1, 2), region.domain)


def _vjp(f, in_shapes, a: torch.Tensor, n: int) -> list[torch.Tensor]:
    """``aᵀ J_f`` for the linear map ``f`` and each of its inputs, batched over ``(B, r)``."""
    xs = [torch.zeros(n, *s, dtype=a.dtype, requires_grad=True) for s in in_shapes]
    with torch.enable_grad():
        y = f(*xs)
        grads = torch.autograd.grad(y, xs, a.reshape(n, *y.shape[1:]), allow_unused=True)
    lead = a.shape[:2]
    return [
        torch.zeros(*lead, *s, dtype=a.dtype) if g is None else g.reshape(*lead, *s)
        for g, s in zip(grads, in_shapes)
    ]


def _maxpool_backward(op, a, best, decided, u_const, H, W):
    """Pull ``a (B, r, C, Ho, Wo)`` through max pooling: lower ``y ≥ x[best]``, upper
    ``y ≤ x[best]`` where decided, else ``y ≤ max u``."""
    B, r, C = a.shape[:3]
    a = a.flatten(3)  # (B, r, C, L)
    a_pos, a_neg = a.clamp_min(0), a.clamp_max(0)
    coef = a_pos + a_neg * decided[:, None]
    const = (a_neg * u_const[:, None]).flatten(2).sum(-1)
    # Input position of each window's chosen element, in the padded frame.
    kw, (sh, sw), (ph, pw) = op.kernel[1], op.stride, op.padding
    Ho, Wo = op.out_size(H, W)
    oy, ox = torch.meshgrid(torch.arange(Ho), torch.arange(Wo), indexing="ij")
    iy = oy.reshape(-1) * sh + best // kw - ph
    ix = ox.reshape(-1) * sw + best % kw - pw
    flat = (iy * W + ix).clamp(0, H * W - 1)  # padding is never the chosen (−inf) element
    grad = torch.zeros(B, r, C, H * W, dtype=a.dtype)
    grad.scatter_add_(3, flat[:, None].expand(B, r, C, -1), coef)
    return [grad.reshape(B, r, C, H, W)], const


def output_bounds(model, input_set, method: str = "forward") -> tuple[torch.Tensor, torch.Tensor]:
    """Sound lower and upper bounds of ``model``'s output over all of ``input_set``.

    Parameters
    ----------
    model : nn.Module
        Built from the operators of :mod:`kpstudy.verify.graph`.
    input_set : ConvexHull, Parallelotope or Box
    method : {'ibp', 'forward', 'crown'}

    Returns
    -------
    lower, upper : Tensor, shape of one output (without batch)

    Examples
    --------
    >>> lo, hi = output_bounds(net, ConvexHull(torch.stack([x0, x1])), "crown")  # doctest: +SKIP
    """
    graph = trace(model, example_input(input_set))
    region = root_region(input_set, graph.dtype)
    idx = torch.arange(graph.output_size)
    none = torch.full_like(idx, -1)
    with torch.no_grad():
        lower = row_bounds(graph, region, idx, none, method)[0]
        upper = -row_bounds(graph, region, none, idx, method)[0]
    shape = graph.nodes[-1].shape
    return lower.reshape(shape), upper.reshape(shape)


def example_input(input_set) -> torch.Tensor:
    """One point of the set as a model input ``(1, *S)`` (for tracing)."""
    first = input_set.lower if input_set.domain == "box" else input_set.vertices[0]
    return first[None]


def root_region(input_set, dtype) -> Region:
    """The whole input set as one region."""
    return node_region(input_set, input_set.root(), dtype)


def node_region(input_set, nodes: torch.Tensor, dtype) -> Region:
    """Regions of ``B`` branch-and-bound nodes of ``input_set``."""
    if input_set.domain == "box":
        lower, upper = input_set.node_bounds(nodes, dtype)
        return Region.interval(lower[:, 0], upper[:, 0])
    coeff, domain = input_set.node_inputs(nodes, dtype)
    return Region.affine(coeff, domain)
