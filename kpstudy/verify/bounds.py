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
``'zonotope'``
    ``'forward'`` plus one error symbol ``ε ∈ [−1, 1]`` per unstable ReLU (DeepZ): the
    ReLU becomes ``s·x + μ + μ·ε`` with ``s = u/(u − l)``, ``μ = −s·l/2``, and the symbols
    are shared by every later value, so the relaxation errors keep their signs through
    the following layers instead of growing as ``|W|·radius``. On the trained CNN this
    is what keeps bounds near the sampled range (``'forward'`` grows ~10× per layer); its
    cost is one pass of every layer per symbol (thousands of symbols on the CNN), on the
    window the symbol reaches: symbols made in one tile of a ReLU share a spatial block
    (:mod:`kpstudy.verify.symbols`) until an operator that mixes space (a pool, a flatten,
    a linear layer) needs the dense stack; the proxy's cell pool reads the blocks itself.
    Symbols are numbered across branches, so two ReLU branches never share one. Past
    :func:`symbol_budget` symbols the smallest further errors go into the radius instead
    (sound, looser).

Floating point: bounds are computed in the graph's dtype; the verifier asks for a
margin above a tolerance or recomputes a node in float64 before it says ``holds``.
"""

from __future__ import annotations

import math
import time

import torch

from kpstudy.verify import ops, symbols
from kpstudy.verify.graph import Graph, trace

METHODS = ("ibp", "forward", "crown", "zonotope")
#: Elements a zonotope's centre stack may hold per region (symbols × the largest
#: activation; 2 GiB in float32): on the paper-sized CNN (131 072 activations in its
#: largest layer) that is 4096 error symbols.
ZONOTOPE_ELEMENTS = 2**29


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


def zonotope_min(a: torch.Tensor, q: int, domain: str) -> torch.Tensor:
    """Exact minimum of ``a[:, :q]`` over ``θ`` (:func:`domain_min`) plus rows ``a[:, q:]``
    over error symbols in ``[−1, 1]``, for ``a (B, q + E, …)``."""
    return domain_min(a[:, :q], domain) - _symbol_reach(a, q)


def _symbol_reach(a: torch.Tensor, q: int):
    """``Σ_e |a[:, q + e]|``: how far the error symbols move each entry (0 without any)."""
    return symbols.l1_rows(a[:, q:]) if a.shape[1] > q else 0.0


class BoundsTimeout(Exception):
    """A bound computation passed its ``deadline`` (between two layers)."""


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

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Concrete lower and upper bounds ``(B, *S)`` over the domain; rows of ``mid``
        past the ``q`` of ``rad`` are error-symbol coefficients (a zonotope), each symbol
        in [−1, 1]."""
        q = self.rad.shape[1]
        spread = symbols.l1_rows(self.mid[:, q:]) if self.mid.shape[1] > q else 0.0
        low = domain_min(self.mid[:, :q] - self.rad, self.domain) - spread
        high = -domain_min(-(self.mid[:, :q] + self.rad), self.domain) + spread
        return low, high

    def to_interval(self) -> Region:
        return Region.interval(*self.bounds())

    @property
    def batch(self) -> int:
        return self.mid.shape[0]


class _State:
    """Per-node pre-activation data kept for the backward pass."""

    def __init__(self) -> None:
        self.relu: dict[int, tuple] = {}  # node → (lower slope, upper slope, upper offset)
        self.maxpool: dict[int, tuple] = {}  # node → (argmax index, decided, upper const)


def propagate(
    graph: Graph,
    region: Region,
    visit=None,
    *,
    zonotope: bool = False,
    max_generators: int | None = None,
    deadline: float | None = None,
) -> tuple[Region, _State]:
    """Forward coefficient bounds of the output for ``B`` regions, and what CROWN needs.

    With ``zonotope``, unstable ReLUs add error-symbol rows to the centre stacks (method
    ``'zonotope'``): a value's ``mid`` is ``(B, q + E, *S)``, its first ``q`` rows the
    affine part in ``θ`` and the others its coefficients on the first ``E`` symbols (at
    most ``max_generators``, default :func:`symbol_budget`); ``rad`` stays
    ``(B, q, *S)``. Inside, the symbols travel in spatial blocks where they can
    (:mod:`kpstudy.verify.symbols`); the output and what ``visit(i, mid, rad)`` (if
    given) sees of every node are dense stacks. Past ``deadline``
    (``time.perf_counter()`` seconds) it raises :class:`BoundsTimeout` between two layers:
    one node of a large zonotope can take minutes.
    """
    B, q = region.mid.shape[:2]
    # A value is (mid, rad, blocks): with ``blocks`` (a list of symbols.Block) ``mid``
    # holds the θ rows only and the symbols live in blocks; with None, ``mid`` is dense.
    values: list[tuple | None] = [None] * len(graph.nodes)
    values[0] = (region.mid, region.rad, [] if zonotope else None)
    remaining = [len(c) for c in graph.consumers]
    state = _State()
    if max_generators is None:
        max_generators = symbol_budget(graph, q)
    made = q  # rows in use: θ rows, then every error symbol made so far (in any branch)

    def dense(value):
        mid, _, blocks = value
        return mid if blocks is None else symbols.dense(mid, blocks, made)

    for i, node in enumerate(graph.nodes[1:], start=1):
        ins = [values[j] for j in node.inputs]
        op = node.op
        in_shapes = [graph.nodes[j].shape for j in node.inputs]
        if op.kind == "affine":
            local = all(v[2] is not None for v in ins) and symbols.is_local(
                op, in_shapes, node.shape
            )
            if ins[0][2] is not None and symbols.is_cell_pool(op):
                mid = symbols.cell_pool(op.m, ins[0][0], ins[0][2], made)
            else:
                mids = [v[0] for v in ins] if local else [dense(v) for v in ins]
                rows = max(m.shape[1] for m in mids)  # symbols made after an input are 0
                mid = _apply(op.linear, [_pad_rows(m, rows) for m in mids], B, rows)
            rad = _apply(op.abs_linear, [v[1] for v in ins], B, q)
            mid = _add_offset(mid, graph.offset(i)[0])
            blocks = None
            if local and len(ins) == 1:
                blocks = symbols.apply(op, ins[0][2], node.shape)
            elif local:
                blocks = symbols.combine(op, [v[2] for v in ins], in_shapes)
            values[i] = (mid, rad, blocks)
        elif op.kind == "relu" and zonotope and ins[0][2] is not None:
            values[i] = _relu_blocks(i, *ins[0], q, made, region.domain, state, max_generators)
            made += sum(b.rows for b in values[i][2] if b.start >= made)
        elif op.kind == "relu" and zonotope:
            mid = _pad_rows(ins[0][0], made)  # new symbols are numbered after all others
            values[i] = (
                *_relu_zonotope(i, mid, ins[0][1], q, region.domain, state, max_generators),
                None,
            )
            made = values[i][0].shape[1]
        elif op.kind == "relu":
            values[i] = (*_relu(i, *ins[0][:2], region.domain, state), None)
        else:
            values[i] = (*_maxpool(i, op, dense(ins[0]), ins[0][1], q, region.domain, state), None)
        if visit is not None:
            visit(i, dense(values[i]), values[i][1])
        if deadline is not None and time.perf_counter() > deadline:
            raise BoundsTimeout
        for j in node.inputs:
            remaining[j] -= 1
            if remaining[j] == 0 and j > 0:
                values[j] = None
    return Region(dense(values[-1]), values[-1][1], region.domain), state


def symbol_budget(graph: Graph, q: int) -> int:
    """Error symbols a zonotope carries on ``graph`` (:data:`ZONOTOPE_ELEMENTS` over its
    largest activation, less the ``q`` affine rows), capped at one per ReLU neuron."""
    biggest = max(math.prod(n.shape) for n in graph.nodes)
    relus = sum(math.prod(n.shape) for n in graph.nodes if n.op and n.op.kind == "relu")
    return max(0, min(relus, ZONOTOPE_ELEMENTS // biggest - q))


def _add_offset(mid: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """``mid (B, q, *S)`` with ``offset (*S)`` added to its constant row; in place unless
    autograd records it (``mid`` may be a view of a value an earlier layer saved)."""
    if mid.requires_grad or offset.requires_grad:
        return torch.cat([mid[:, :1] + offset, mid[:, 1:]], 1)
    mid[:, 0] += offset
    return mid


def _pad_rows(x: torch.Tensor, rows: int) -> torch.Tensor:
    if x.shape[1] == rows:
        return x
    return torch.cat([x, x.new_zeros(x.shape[0], rows - x.shape[1], *x.shape[2:])], 1)


def _apply(f, xs: list[torch.Tensor], B: int, q: int) -> torch.Tensor:
    y = f(*(x.reshape(B * q, *x.shape[2:]) for x in xs))
    return y.reshape(B, q, *y.shape[1:])


def _interval(mid, rad, q, domain):
    """Concrete lower and upper bounds ``(B, *S)`` of a (zonotope) value."""
    reach = _symbol_reach(mid, q)  # the same either way
    low = domain_min(mid[:, :q] - rad, domain) - reach
    high = -domain_min(-mid[:, :q] - rad, domain) + reach
    return low, high


def _relu(i, mid, rad, domain, state):
    low, up = mid - rad, mid + rad
    l = domain_min(low, domain)
    u = -domain_min(-up, domain)
    active, dead = l >= 0, u <= 0
    unstable = ~(active | dead)
    s = torch.where(unstable, u / (u - l).clamp_min(1e-30), active.to(mid.dtype))
    # The lower line: slope 1 or 0, whichever leaves the smaller area. An interval has no
    # θ to carry, so there it is 0: max(l, 0), textbook interval arithmetic.
    steep = (u > -l) if mid.shape[1] > 1 else torch.zeros_like(unstable)
    alpha = torch.where(unstable, steep.to(mid.dtype), active.to(mid.dtype))
    offset = torch.where(unstable, -s * l, torch.zeros_like(l))  # upper: s·z − s·l
    state.relu[i] = (alpha, s, offset)
    new_low, new_up = alpha[:, None] * low, s[:, None] * up
    new_up[:, 0] += offset
    return (new_up + new_low) / 2, (new_up - new_low) / 2


def _deepz(i, l, u, state):
    """DeepZ's slope ``s`` and offset ``μ`` (``0`` where stable) of ReLUs with
    pre-activation bounds ``l, u``; keeps the triangle relaxation for a backward pass."""
    active, dead = l >= 0, u <= 0
    unstable = ~(active | dead)
    s = torch.where(unstable, u / (u - l).clamp_min(1e-30), active.to(l.dtype))
    mu = torch.where(unstable, -s * l / 2, torch.zeros_like(l))
    alpha = torch.where(unstable, (u > -l).to(l.dtype), active.to(l.dtype))
    state.relu[i] = (alpha, s, 2 * mu)
    return s, mu


def _relu_zonotope(i, mid, rad, q, domain, state, max_generators):
    """DeepZ: ``s·x + μ + μ·ε_new`` for each unstable ReLU (a new symbol), ``x`` if active,
    0 if dead; past ``max_generators`` symbols the smallest new ``μ`` go to the radius."""
    l, u = _interval(mid, rad, q, domain)
    s, mu = _deepz(i, l, u, state)
    B, rows = mid.shape[:2]
    flat_mu = mu.reshape(B, -1)
    k = min(int((flat_mu > 0).sum(1).max()), max(0, max_generators - (rows - q)))
    order = flat_mu.argsort(1, descending=True)[:, :k]  # the k largest μ of each region
    out = mid.new_empty(B, rows + k, *mu.shape[1:])  # written once: the stacks are large
    torch.mul(mid, s[:, None], out=out[:, :rows])
    out[:, 0] += mu
    symbols = out[:, rows:].view(B, k, flat_mu.shape[1])
    symbols.zero_()
    symbols.scatter_(2, order[:, :, None], flat_mu.gather(1, order)[:, :, None])
    new_rad = s[:, None] * rad
    new_rad[:, 0] += flat_mu.scatter(1, order, 0.0).reshape(mu.shape)  # the rest: radius
    return out, new_rad


def _relu_blocks(i, mid, rad, blocks, q, made, domain, state, max_generators):
    """:func:`_relu_zonotope` on a value whose symbols are in blocks (:mod:`symbols`): the
    old symbols are scaled by the slopes, the new ones grouped by tile."""
    reach = symbols.reach(blocks, mid[:, 0])
    l = domain_min(mid - rad, domain) - reach
    u = -domain_min(-mid - rad, domain) + reach
    s, mu = _deepz(i, l, u, state)
    B = mid.shape[0]
    flat_mu = mu.reshape(B, -1)
    left = max(0, max_generators - (made - q))
    k = min(int((flat_mu > 0).sum(1).max()), left)
    while True:  # the k largest μ of each region, fewer if the tiles' rows pass the budget
        kept = torch.zeros_like(flat_mu)
        if k > 0:
            top = flat_mu.topk(k, 1)
            kept.scatter_(1, top.indices, top.values)
        new = symbols.make(kept.view_as(mu), made)
        rows = sum(b.rows for b in new)
        if rows <= left:
            break
        k = min(k - 1, k * left // rows)
    new_mid = mid * s[:, None]
    new_mid[:, 0] += mu
    new_rad = s[:, None] * rad
    new_rad[:, 0] += (flat_mu - kept).view_as(mu)  # the rest: radius
    return new_mid, new_rad, symbols.scale(blocks, s) + new


def _maxpool(i, op: ops.MaxPool, mid, rad, q, domain, state):
    """Decided windows pass their largest-lower-bound input; undecided ones are bounded
    below by it and above by the window's largest upper bound (with error symbols, the
    interval between its concrete lower bound and that)."""
    B, rows, C, H, W = mid.shape
    l, u = _interval(mid, rad, q, domain)
    lw, uw = op.windows(l, float("-inf")), op.windows(u, float("-inf"))  # (B, C, k, L)
    best = lw.argmax(2, keepdim=True)
    l_best = lw.gather(2, best)
    others = uw.scatter(2, best, float("-inf")).amax(2, keepdim=True)
    decided = (l_best >= others)[:, :, 0]  # (B, C, L)
    l_best = l_best[:, :, 0]
    u_max = uw.amax(2)
    Ho, Wo = op.out_size(H, W)

    def pick(x):
        r = x.shape[1]
        win = op.windows(x.reshape(B * r, C, H, W), 0.0).reshape(B, r, C, -1, Ho * Wo)
        return win.gather(3, best[:, None].expand(B, r, C, 1, Ho * Wo))[:, :, :, 0]

    keep = decided[:, None]
    zero = torch.zeros((), dtype=mid.dtype)
    if rows == q:  # no symbols: keep the chosen input's lower bound linear in θ
        low, up = pick(mid - rad), torch.where(keep, pick(mid + rad), zero)
        up[:, 0] += torch.where(decided, zero, u_max)
        new_mid, new_rad = (up + low) / 2, (up - low) / 2
    else:
        new_mid = torch.where(keep, pick(mid), zero)
        new_rad = torch.where(keep, pick(rad), zero)
        new_mid[:, 0] += torch.where(decided, zero, (l_best + u_max) / 2)
        new_rad[:, 0] += torch.where(decided, zero, (u_max - l_best) / 2)
    state.maxpool[i] = (best[:, :, 0], decided, torch.where(decided, zero, u_max), (H, W))
    return new_mid.reshape(B, rows, C, Ho, Wo), new_rad.reshape(B, q, C, Ho, Wo)


# -- margins -------------------------------------------------------------------------------


def row_bounds(
    graph: Graph,
    region: Region,
    pos: torch.Tensor,
    neg: torch.Tensor,
    method: str = "forward",
    *,
    memory: int = 2**25,
    deadline: float | None = None,
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
    method : {'ibp', 'forward', 'crown', 'zonotope'}
    memory : int
        Largest backward coefficient tensor, in elements (``'crown'`` chunks rows by it).
    deadline : float, optional
        ``time.perf_counter()`` past which :class:`BoundsTimeout` is raised.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "ibp":
        region = region.to_interval()
    q = region.mid.shape[1]
    out, state = propagate(graph, region, zonotope=method == "zonotope", deadline=deadline)
    mid, rad = out.mid.flatten(2), out.rad.flatten(2)
    zero = torch.zeros((), dtype=mid.dtype)

    def take(x, index):  # x[..., index], 0 where index is −1
        return torch.where((index >= 0)[None, None], x[..., index.clamp_min(0)], zero)

    coeff = take(mid, pos) - take(mid, neg)  # (B, q + E, R): the margin's symbols cancel
    coeff[:, :q] -= take(rad, pos) + take(rad, neg)
    lower = zonotope_min(coeff, q, out.domain)
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


def _backward(
    graph: Graph, region: Region, state: _State, pos, neg, start: int = -1
) -> torch.Tensor:
    """CROWN lower bounds ``(B, r)`` of ``y[pos] − y[neg]``: a linear lower bound of each
    row pulled back to the input, then minimised exactly over the region.

    ``y`` is node ``start`` (default: the output), flat; ``state`` holds the relaxations of
    the nodes before it."""
    B, r = region.batch, len(pos)
    dtype = region.mid.dtype
    start = start % len(graph.nodes)
    out = graph.nodes[start]
    seed = torch.zeros(B, r, math.prod(out.shape), dtype=dtype)
    rows = torch.arange(r)
    seed[:, rows[pos >= 0], pos[pos >= 0]] = 1.0
    seed[:, rows[neg >= 0], neg[neg >= 0]] -= 1.0
    A: dict[int, torch.Tensor] = {start: seed.reshape(B, r, *out.shape)}
    const = torch.zeros(B, r, dtype=dtype)
    for i in range(start, 0, -1):
        a = A.pop(i, None)
        if a is None:
            continue
        node = graph.nodes[i]
        op = node.op
        if op.kind == "affine":
            const += (a * graph.offset(i)[None]).flatten(2).sum(-1)
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
    method : {'ibp', 'forward', 'crown', 'zonotope'}

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
