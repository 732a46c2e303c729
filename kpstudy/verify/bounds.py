"""Sound bounds of a traced network over an input set, in the set's few parameters.

A batch of ``B`` regions (branch-and-bound nodes, each input set's
:meth:`~kpstudy.verify.sets.ConvexHull.region`) enters as affine inputs
``x = c + Σ_i θ_i G_i`` with ``θ`` in a *domain* — the standard simplex
``{θ ≥ 0, Σ θ ≤ 1}`` for a convex hull, the unit cube for a parallelotope — or, for a
box, as an interval (no ``θ``). Every value of the network is then bounded by two affine
functions of ``θ``, stored as coefficient stacks ``(B, q, *shape)`` (row 0 the constant,
rows 1… the ``θ`` coefficients) in centre/radius form: lower ``mid − rad``, upper
``mid + rad`` (``kpstudy.verify.region.Region``). The minimum of ``a0 + a·θ`` is
exact: ``a0 + min(0, min_i a_i)`` over the simplex, ``a0 + Σ_i min(0, a_i)`` over the
cube. This module runs the passes; each operator's rules for every method are in
``kpstudy.verify.operators``.

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
    window the symbol reaches: each symbol keeps its own window, the symbols of one ReLU
    in one block (``kpstudy.verify.symbols``), until an operator that mixes space (a
    flatten, a linear layer) needs the dense stack; the proxy's cell pool reads the
    blocks itself, and a max pooling copies each window's chosen input's symbols (an
    undecided window adds one symbol for its excess over that input).
    Symbols are numbered across branches, so two ReLU branches never share one. Their
    memory is budgeted in elements (:data:`ZONOTOPE_ELEMENTS` per region): a symbol costs
    the most its coefficients ever hold (:func:`symbol_footprints`: its window's extent
    through the blocks, a whole value once it is dense), and past the budget the smallest
    further errors of a ReLU or a max pooling go into the radius instead (sound, looser).

Floating point: bounds are computed in the graph's dtype; the verifier asks for a
margin above a tolerance or recomputes a node in float64 before it says ``holds``.
"""

from __future__ import annotations

import math
import time
import weakref

import torch

from kpstudy import _checks
from kpstudy.verify import operators, symbols
from kpstudy.verify.graph import Graph, trace
from kpstudy.verify.region import Region, domain_min, symbol_reach

METHODS = ("ibp", "forward", "crown", "zonotope")
#: Elements a zonotope's error symbols may hold per region (2 GiB in float32), each symbol
#: counted at its :func:`symbol_footprints`: as dense rows on the paper-sized CNN (131 072
#: activations in its largest layer) that would be 4096 symbols.
ZONOTOPE_ELEMENTS = 2**29


def zonotope_min(a: torch.Tensor, q: int, domain: str) -> torch.Tensor:
    """Exact minimum of ``a[:, :q]`` over ``θ`` (``domain_min()``) plus rows ``a[:, q:]``
    over error symbols in ``[−1, 1]``, for ``a (B, q + E, …)``."""
    return domain_min(a[:, :q], domain) - symbol_reach(a, q)


class BoundsTimeout(Exception):
    """A bound computation passed its ``deadline`` (between two layers)."""


def propagate(
    graph: Graph,
    region: Region,
    visit=None,
    *,
    zonotope: bool = False,
    max_generators: int | None = None,
    deadline: float | None = None,
    dense: bool = True,
) -> tuple[Region, dict]:
    """Forward coefficient bounds of the output for ``B`` regions, and what CROWN needs
    (node → what its rule saved, for :func:`backward`).

    Each node is bounded by its operator's rules (``kpstudy.verify.operators``).

    With ``zonotope``, unstable ReLUs add error-symbol rows to the centre stacks (method
    ``'zonotope'``): a value's ``mid`` is ``(B, q + E, *S)``, its first ``q`` rows the
    affine part in ``θ`` and the others its coefficients on the first ``E`` symbols (at
    most ``max_generators`` if given, and within :data:`ZONOTOPE_ELEMENTS`); ``rad`` stays
    ``(B, q, *S)``. Inside, the symbols travel in spatial blocks where they can
    (``kpstudy.verify.symbols``); what ``visit(i, value)`` (if given) sees of
    every node is a dense ``Region``, and so is the output unless ``dense`` is False: then an
    output that holds its symbols in blocks keeps them (``Region.blocks``), for a
    caller that reads a few entries' symbols (``Region.symbols_at()``) of an output
    whose dense stack (symbols × outputs) would dwarf the pass itself. A ``region`` that
    holds symbols already (an earlier pass's output: the head of
    ``kpstudy.verify.graph.Graph.split_affine_tail()``) carries them on, numbering new
    ones after its ``rows``; it needs ``zonotope``. Past ``deadline``
    (``time.perf_counter()`` seconds) it raises :class:`BoundsTimeout` between two layers:
    one node of a large zonotope can take minutes.
    """
    q = region.rad.shape[1]
    elements = ZONOTOPE_ELEMENTS - q * max(math.prod(n.shape) for n in graph.nodes)
    p = operators.Pass(
        graph, q, region.domain, max_generators, symbol_footprints(graph), max(0, elements)
    )
    values: list[Region | None] = [None] * len(graph.nodes)
    if region.blocks is not None or region.mid.shape[1] > q:  # symbols of an earlier pass
        if not zonotope:
            raise ValueError("region: a region with error symbols needs zonotope=True")
        p.made = region.rows if region.blocks is not None else region.mid.shape[1]
        values[0] = region
    else:
        values[0] = Region(region.mid, region.rad, region.domain, [] if zonotope else None)
    remaining = [len(c) for c in graph.consumers]
    for i, node in enumerate(graph.nodes[1:], start=1):
        rule = operators.rules(node.op.kind)
        step = rule.zonotope if zonotope else rule.forward
        values[i] = step(p, i, [values[j] for j in node.inputs])
        if visit is not None:
            visit(i, Region(p.dense(values[i]), values[i].rad, region.domain))
        if deadline is not None and time.perf_counter() > deadline:
            raise BoundsTimeout
        for j in node.inputs:
            remaining[j] -= 1
            if remaining[j] == 0 and j > 0:
                values[j] = None
    out = values[-1]
    if out.blocks is not None and not dense:
        return Region(out.mid, out.rad, region.domain, out.blocks, p.made), p.saved
    return Region(p.dense(out), out.rad, region.domain), p.saved


def zonotope_elements(graph: Graph, q: int) -> int:
    """Elements a zonotope's centre stack holds at most per region on ``graph``: the
    ``q`` affine rows of its largest value, then :data:`ZONOTOPE_ELEMENTS` or, if less,
    one symbol per ReLU neuron at its footprint (:func:`symbol_footprints`)."""
    biggest = max(math.prod(n.shape) for n in graph.nodes)
    every = sum(
        math.prod(graph.nodes[i].shape) * cost for i, cost in symbol_footprints(graph).items()
    )
    return q * biggest + min(every, ZONOTOPE_ELEMENTS)


_FOOTPRINTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def symbol_footprints(graph: Graph) -> dict[int, int]:
    """Per symbol-making node (a ReLU, a max pooling) ``i``: the most elements one error
    symbol made there holds in any later value, per region (the zonotope's memory budget
    counts symbols at this).

    While a value's symbols travel in blocks (``kpstudy.verify.symbols``), a symbol
    holds its window: a ``1 × 1`` window at the middle of node ``i`` is mapped through the
    later local operators as the pass maps it (the windows' extents, not their values);
    from the first operator that reads the dense stack on, it holds whole values. A
    symbol made where the stack is dense holds the largest later value. Computed once
    per graph."""
    if graph in _FOOTPRINTS:
        return _FOOTPRINTS[graph]
    nodes = graph.nodes
    sizes = [math.prod(n.shape) for n in nodes]
    later = [max(sizes[i:]) for i in range(len(nodes))]  # the largest value from i on
    blocked = [True] + [False] * (len(nodes) - 1)  # whether a value keeps symbols in blocks
    for j, node in enumerate(nodes[1:], start=1):
        ins = [nodes[k].shape for k in node.inputs]
        rule = operators.rules(node.op.kind)
        through = rule.makes_symbols or (
            rule.keeps_blocks and symbols.is_local(node.op, ins, node.shape)
        )
        blocked[j] = through and all(blocked[k] for k in node.inputs)
    out = {}
    with torch.no_grad():
        for i, node in enumerate(nodes):
            if i == 0 or not operators.rules(node.op.kind).makes_symbols:
                continue
            if not (blocked[i] and len(node.shape) == 3):
                out[i] = later[i]
                continue
            C, H, W = node.shape
            one = torch.ones(1, 1, C, 1, 1, dtype=graph.dtype)
            middle = torch.tensor([[H // 2]]), torch.tensor([[W // 2]])
            reach = {i: [symbols.Block(one, 0, *middle)]}
            cost = C
            for j in range(i + 1, len(nodes)):
                after = nodes[j]
                held = [reach.get(k) for k in after.inputs]
                if all(h is None for h in held):
                    continue
                if not blocked[j]:
                    cost = max(cost, later[j])
                    break
                rule = operators.rules(after.op.kind)
                if rule.makes_symbols and not rule.keeps_blocks:  # element-wise: the same
                    reach[j] = held[0]
                elif len(held) == 1:
                    reach[j] = symbols.apply(after.op, held[0], after.shape)
                else:
                    shapes = [nodes[k].shape for k in after.inputs]
                    reach[j] = symbols.combine(after.op, [h or [] for h in held], shapes)
                cost = max(cost, sum(b.coeff[0, 0].numel() for b in reach[j]))
            out[i] = cost
    _FOOTPRINTS[graph] = out
    return out


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
    _checks.choice(method, "method", METHODS)
    if method == "ibp":
        region = region.to_interval()
    q = region.mid.shape[1]
    out, saved = propagate(graph, region, zonotope=method == "zonotope", deadline=deadline)
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
            backward(graph, region, saved, pos[s], neg[s])
            for s in _chunks(len(pos), region, graph, memory)
        ],
        1,
    )
    return torch.maximum(lower, crown)


def _chunks(R: int, region: Region, graph: Graph, memory: int):
    biggest = max(math.prod(n.shape) for n in graph.nodes)
    step = max(1, memory // (region.batch * biggest))
    return [slice(a, min(a + step, R)) for a in range(0, R, step)]


def backward(graph: Graph, region: Region, saved: dict, pos, neg, start: int = -1) -> torch.Tensor:
    """CROWN lower bounds ``(B, r)`` of ``y[pos] − y[neg]``: a linear lower bound of each
    row pulled back to the input through each node's rules, then minimised exactly over
    the region.

    ``y`` is node ``start`` (default: the output), flat; ``saved`` (from
    :func:`propagate`) holds the relaxations of the nodes before it."""
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
        grads, c = operators.rules(node.op.kind).backward(graph, i, a, saved.get(i))
        const += c
        for j, g in zip(node.inputs, grads):
            A[j] = g if j not in A else A[j] + g
    a = A.pop(0).flatten(2)  # (B, r, d)
    mid, rad = region.mid.flatten(2), region.rad.flatten(2)  # (B, q, d)
    coeff = torch.einsum("brd,bqd->brq", a, mid) - torch.einsum("brd,bqd->brq", a.abs(), rad)
    coeff[..., 0] += const
    return domain_min(coeff.transpose(1, 2), region.domain)


def output_bounds(model, input_set, method: str = "forward") -> tuple[torch.Tensor, torch.Tensor]:
    """Sound lower and upper bounds of ``model``'s output over all of ``input_set``.

    Parameters
    ----------
    model : nn.Module
        Built from the operators of ``kpstudy.verify.graph``.
    input_set : ConvexHull, Parallelotope or Box
    method : {'ibp', 'forward', 'crown', 'zonotope'}

    Returns
    -------
    lower, upper : Tensor, shape of one output (without batch)

    Examples
    --------
    >>> lo, hi = output_bounds(net, ConvexHull(torch.stack([x0, x1])), "crown")  # doctest: +SKIP
    """
    graph = trace(model, input_set.example_input())
    region = input_set.region(input_set.root(), graph.dtype)
    idx = torch.arange(graph.output_size)
    none = torch.full_like(idx, -1)
    with torch.no_grad():
        lower = row_bounds(graph, region, idx, none, method)[0]
        upper = -row_bounds(graph, region, none, idx, method)[0]
    shape = graph.nodes[-1].shape
    return lower.reshape(shape), upper.reshape(shape)
