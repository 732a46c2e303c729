"""The bound rules of each operator kind, one class per kind, found through :data:`RULES`.

:func:`kpstudy.verify.bounds.propagate` and :func:`~kpstudy.verify.bounds.backward` look
up ``RULES[node.op.kind]`` (:func:`rules`) for every node of a traced graph and call:

``forward(p, i, ins)``
    Bounds of node ``i`` from its inputs' values, as coefficient stacks in ``θ``
    (methods ``'ibp'`` and ``'forward'``; ``'ibp'`` is this rule on an interval region,
    ``q = 1``, so interval arithmetic needs no rule of its own).
``zonotope(p, i, ins)``
    The same with error symbols (method ``'zonotope'``); by default ``forward`` with the
    inputs' symbols moved into their radius (sound, but what they share is lost).
``backward(graph, i, a, saved)``
    CROWN: a linear lower bound ``a · y_i`` pulled back to the inputs of node ``i``, from
    what ``forward``/``zonotope`` saved for it (``p.saved[i]``): the input coefficients
    and the constant it adds.
``profile(low, high, low_s, high_s)``
    Extra columns of :func:`kpstudy.verify.profile.bound_profile` from the input's
    bounds and sampled range (the ReLU: unstable neurons).

A value is a :class:`~kpstudy.verify.region.Region`: coefficient stacks ``mid (B, rows,
*S)``, ``rad (B, q, *S)`` (lower ``mid − rad``, upper ``mid + rad``, row 0 the constant,
rows ``1 … q−1`` the ``θ`` coefficients, rows from ``q`` on error symbols), and, inside a
zonotope pass, ``blocks`` (a list of :class:`kpstudy.verify.symbols.Block`) holding the
symbols while ``mid`` holds the ``θ`` rows only; ``blocks`` is ``None`` when ``mid`` is
dense. Affine operators (:mod:`kpstudy.verify.ops`) share one rule, :class:`AffineRules`,
derived from their three maps; each says itself how symbol blocks go through it.

Adding a layer
--------------
1. The operator: an :class:`kpstudy.verify.ops.Op` with its concrete ``forward`` and a
   ``kind``. An affine layer gives ``linear``/``abs_linear`` too (by default ``forward``
   and ``linear``: a map without bias and with weights ≥ 0 needs neither), keeps
   ``kind = 'affine'``, and is done after step 3; if it maps each error symbol's window
   to a window, it says so (``local``) and how (``map_window``), and a zonotope's
   symbols stay in blocks through it.
2. Its rules: a :class:`Rules` subclass with ``forward`` and ``backward`` (and
   ``zonotope``, ``profile`` where the defaults do not fit), registered as
   ``RULES[kind] = MyRules()``. Every bound must contain every value the layer takes on
   the region; the tests check it against samples.
3. Tracing: ``kpstudy.verify.graph.MODULES[MyModule] = lambda m: MyOp(...)`` (or a case
   in ``graph._operator`` for a function).

No other module changes. For example, a leaky ReLU ``y = max(x, c·x)`` (``0 ≤ c ≤ 1``)
between bounds ``l, u`` is the identity where ``l ≥ 0``, ``c·x`` where ``u ≤ 0`` and
otherwise lies between the line ``c·x`` and the chord ``s·x + t``
(``s = (u − c·l)/(u − l)``, ``t = (c − s)·l``); a nearest-neighbour upsampling by two is
linear with weights ≥ 0 and maps a window to one of twice its size at twice its corner::

    class LeakyReLU(ops.Op):
        kind = "leaky_relu"
        def __init__(self, c): self.c = c
        def forward(self, x): return F.leaky_relu(x, self.c)

    class LeakyReLURules(Rules):
        def forward(self, p, i, ins):
            low, up = ins[0].mid - ins[0].rad, ins[0].mid + ins[0].rad
            l, u = ins[0].bounds()
            c = p.graph.nodes[i].op.c
            lo_slope = torch.where(l >= 0, 1.0, torch.full_like(l, c))
            s = torch.where(u <= 0, c, (u - c * l) / (u - l).clamp_min(1e-30))
            s = torch.where(l >= 0, 1.0, s)
            t = (c - s) * l.clamp_max(0)  # 0 where stable
            p.saved[i] = (lo_slope, s, t)
            new_low, new_up = lo_slope[:, None] * low, s[:, None] * up
            new_up[:, 0] += t
            return Region.between(new_low, new_up, p.domain)
        def backward(self, graph, i, a, saved):
            lo_slope, s, t = saved
            a_pos, a_neg = a.clamp_min(0), a.clamp_max(0)
            const = (a_neg * t[:, None]).flatten(2).sum(-1)
            return [a_pos * lo_slope[:, None] + a_neg * s[:, None]], const

    RULES["leaky_relu"] = LeakyReLURules()
    graph.MODULES[nn.LeakyReLU] = lambda m: LeakyReLU(m.negative_slope)

    class Upsample2(ops.Op):
        local = True
        def forward(self, x): return F.interpolate(x, scale_factor=2.0, mode="nearest")
        def map_window(self, x, y, x0, out_hw): return self.forward(x), 2 * y, 2 * x0

    graph.MODULES[nn.Upsample] = lambda m: Upsample2()

``tests/kpstudy/verify/test_operators.py`` runs these examples through every method.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
import torch.nn.functional as F

from kpstudy.verify import ops, symbols
from kpstudy.verify.region import Region, domain_min


class Pass:
    """One forward pass of ``B`` regions through ``graph``: what the rules share.

    Attributes
    ----------
    graph : Graph
    q : int
        ``θ`` rows (1 for an interval region).
    domain : str
        ``'simplex'``, ``'cube'`` or ``'point'``.
    max_generators : int or None
        Error symbols a zonotope may make in all (None: no count).
    footprints : dict
        Symbol-making node → elements one of its symbols holds at most, per region
        (:func:`kpstudy.verify.bounds.symbol_footprints`).
    elements : int
        Elements, per region, the symbols still to be made may hold (each at its
        footprint).
    made : int
        Rows of the dense stack in use: the ``θ`` rows, then every symbol made so far (in
        any branch), so that a new symbol never shares a number.
    saved : dict
        Node index → what its ``backward`` rule needs.
    """

    def __init__(
        self, graph, q: int, domain: str, max_generators, footprints: dict, elements: int
    ) -> None:
        self.graph, self.q, self.domain = graph, q, domain
        self.max_generators = max_generators
        self.footprints, self.elements = footprints, elements
        self.made = q
        self.saved: dict[int, tuple] = {}

    def allow(self, i: int, wanted: int) -> int:
        """How many of ``wanted`` new symbols node ``i`` may make (the count cap and the
        element budget), charged to the budget."""
        left = self.elements // self.footprints[i]
        if self.max_generators is not None:
            left = min(left, self.max_generators - (self.made - self.q))
        k = max(0, min(wanted, left))
        self.elements -= k * self.footprints[i]
        return k

    def dense(self, value: Region) -> torch.Tensor:
        """The dense stack ``(B, rows, *S)`` of a value."""
        if value.blocks is None:
            return value.mid
        return symbols.dense(value.mid, value.blocks, self.made)

    def without_symbols(self, value: Region) -> Region:
        """A value's ``θ`` rows, its symbols' reach added to the radius."""
        return Region(self.dense(value), value.rad, self.domain).without_symbols()


class Rules(ABC):
    """The bound rules of one operator kind (see the module docstring): a subclass writes
    ``forward`` and ``backward``; ``zonotope`` and ``profile`` have sound defaults."""

    #: Whether the zonotope makes up to one error symbol per neuron of such a node.
    makes_symbols = False
    #: Whether its ``zonotope`` rule keeps a value's symbols in blocks where its operator
    #: is local (``kpstudy.verify.ops.Op.local``).
    keeps_blocks = False

    @abstractmethod
    def forward(self, p: Pass, i: int, ins: list[Region]) -> Region:
        """Node ``i``'s value from its inputs' values ``ins`` (interval, forward and
        ``ibp`` passes)."""

    def zonotope(self, p: Pass, i: int, ins: list[Region]) -> Region:
        """``forward`` with each input's error symbols moved into its radius (sound; what
        the symbols share is lost at this node)."""
        return self.forward(p, i, [p.without_symbols(v) for v in ins])

    @abstractmethod
    def backward(self, graph, i: int, a: torch.Tensor, saved) -> tuple[list, torch.Tensor]:
        """``a (B, r, *S_i)`` → one coefficient tensor per input and the constant
        ``(B, r)`` of the pulled-back lower bound."""

    def profile(self, low, high, low_s, high_s) -> dict:
        return {}


class AffineRules(Rules):
    """Every affine operator, from its maps (:mod:`kpstudy.verify.ops`): exact. A
    zonotope's symbol blocks go through the operators that map them
    (:attr:`~kpstudy.verify.ops.Op.local`, :meth:`~kpstudy.verify.ops.Op.map_window`);
    one that reads them itself (:meth:`~kpstudy.verify.ops.Op.read_blocks`, the cell
    pool) gives the dense stack of its output; any other reads the dense stack."""

    keeps_blocks = True

    def forward(self, p, i, ins):
        node = p.graph.nodes[i]
        op = node.op
        in_shapes = [p.graph.nodes[j].shape for j in node.inputs]
        B = ins[0].batch
        blocked = all(v.blocks is not None for v in ins)
        local = blocked and symbols.is_local(op, in_shapes, node.shape)
        mid = op.read_blocks(ins[0].mid, ins[0].blocks, p.made) if blocked else None
        if mid is None:
            mids = [v.mid for v in ins] if local else [p.dense(v) for v in ins]
            rows = max(m.shape[1] for m in mids)  # symbols made after an input are 0
            mid = _apply(op.linear, [_pad_rows(m, rows) for m in mids], B, rows)
        rad = _apply(op.abs_linear, [v.rad for v in ins], B, p.q)
        mid = _add_offset(mid, p.graph.offset(i)[0])
        blocks = None
        if local and len(ins) == 1:
            blocks = symbols.apply(op, ins[0].blocks, node.shape)
        elif local:
            blocks = symbols.combine(op, [v.blocks for v in ins], in_shapes)
        return Region(mid, rad, p.domain, blocks)

    zonotope = forward  # blocks pass through convolutions and the cell pool

    def backward(self, graph, i, a, saved):
        node = graph.nodes[i]
        B, r = a.shape[:2]
        const = (a * graph.offset(i)[None]).flatten(2).sum(-1)
        grads = _vjp(node.op.linear, [graph.nodes[j].shape for j in node.inputs], a, B * r)
        return grads, const


class ReLURules(Rules):
    """``forward``: the triangle relaxation (lower slope 0 or 1, whichever leaves the
    smaller area; upper the chord). ``zonotope``: DeepZ, ``s·x + μ + μ·ε`` with one new
    symbol ``ε`` per unstable neuron (``s = u/(u − l)``, ``μ = −s·l/2``); past the
    pass's budget (:meth:`Pass.allow`) the smallest ``μ`` go to the radius."""

    makes_symbols = True

    def forward(self, p, i, ins):
        mid, rad = ins[0].mid, ins[0].rad
        low, up = mid - rad, mid + rad
        l = domain_min(low, p.domain)
        u = -domain_min(-up, p.domain)
        active, dead = l >= 0, u <= 0
        unstable = ~(active | dead)
        s = torch.where(unstable, u / (u - l).clamp_min(1e-30), active.to(mid.dtype))
        # The lower line: slope 1 or 0, whichever leaves the smaller area. An interval has
        # no θ to carry, so there it is 0: max(l, 0), textbook interval arithmetic.
        steep = (u > -l) if mid.shape[1] > 1 else torch.zeros_like(unstable)
        alpha = torch.where(unstable, steep.to(mid.dtype), active.to(mid.dtype))
        offset = torch.where(unstable, -s * l, torch.zeros_like(l))  # upper: s·z − s·l
        p.saved[i] = (alpha, s, offset)
        new_low, new_up = alpha[:, None] * low, s[:, None] * up
        new_up[:, 0] += offset
        return Region.between(new_low, new_up, p.domain)

    def zonotope(self, p, i, ins):
        if ins[0].blocks is not None:
            return self._blocks(p, i, ins[0])
        mid = _pad_rows(ins[0].mid, p.made)  # new symbols are numbered after all others
        value = self._dense(p, i, Region(mid, ins[0].rad, p.domain))
        p.made = value.mid.shape[1]
        return value

    def backward(self, graph, i, a, saved):
        alpha, s, offset = saved
        a_pos, a_neg = a.clamp_min(0), a.clamp_max(0)
        const = (a_neg * offset[:, None]).flatten(2).sum(-1)
        return [a_pos * alpha[:, None] + a_neg * s[:, None]], const

    def profile(self, low, high, low_s, high_s):
        return {
            "unstable_bound": int(((low < 0) & (high > 0)).sum()),
            "unstable_sampled": int(((low_s < 0) & (high_s > 0)).sum()),
        }

    @staticmethod
    def _deepz(p, i, l, u):
        """DeepZ's slope ``s`` and offset ``μ`` (``0`` where stable) for pre-activation
        bounds ``l, u``; saves the triangle relaxation for a backward pass."""
        active, dead = l >= 0, u <= 0
        unstable = ~(active | dead)
        s = torch.where(unstable, u / (u - l).clamp_min(1e-30), active.to(l.dtype))
        mu = torch.where(unstable, -s * l / 2, torch.zeros_like(l))
        alpha = torch.where(unstable, (u > -l).to(l.dtype), active.to(l.dtype))
        p.saved[i] = (alpha, s, 2 * mu)
        return s, mu

    def _dense(self, p, i, x):
        """DeepZ on a dense stack: ``s·x + μ + μ·ε_new`` per unstable ReLU."""
        mid, rad = x.mid, x.rad
        l, u = x.bounds()
        s, mu = self._deepz(p, i, l, u)
        B, rows = mid.shape[:2]
        flat_mu = mu.reshape(B, -1)
        k = p.allow(i, int((flat_mu > 0).sum(1).max()))
        order = flat_mu.argsort(1, descending=True)[:, :k]  # the k largest μ of each region
        out = mid.new_empty(B, rows + k, *mu.shape[1:])  # written once: the stacks are large
        torch.mul(mid, s[:, None], out=out[:, :rows])
        out[:, 0] += mu
        new = out[:, rows:].view(B, k, flat_mu.shape[1])
        new.zero_()
        new.scatter_(2, order[:, :, None], flat_mu.gather(1, order)[:, :, None])
        new_rad = s[:, None] * rad
        new_rad[:, 0] += flat_mu.scatter(1, order, 0.0).reshape(mu.shape)  # the rest: radius
        return Region(out, new_rad, p.domain)

    def _blocks(self, p, i, x):
        """DeepZ on a value whose symbols are in blocks (:mod:`symbols`): the old symbols
        are scaled by the slopes, the new ones make one block."""
        mid, rad = x.mid, x.rad
        l, u = x.bounds()
        s, mu = self._deepz(p, i, l, u)
        kept = _budgeted(p, i, mu)
        new = symbols.make(kept, p.made)
        new_mid = mid * s[:, None]
        new_mid[:, 0] += mu
        new_rad = s[:, None] * rad
        new_rad[:, 0] += mu - kept  # the rest: radius
        p.made += sum(b.rows for b in new)
        return Region(new_mid, new_rad, p.domain, symbols.scale(x.blocks, s) + new)


class MaxPoolRules(Rules):
    """Decided windows (largest lower bound ≥ every other upper bound) pass their
    largest-lower-bound input ``x_c``; undecided ones are bounded below by it and above by
    the window's largest upper bound. ``zonotope``: every window passes ``x_c`` with its
    error symbols, and an undecided one adds its excess ``max_j x_j − x_c ∈ [0, 2μ]``
    (``2μ`` the largest other upper bound less ``x_c``'s lower bound) as ``μ + μ·ε``, one
    new symbol per window (past the pass's budget, :meth:`Pass.allow`, the smallest go
    to the radius). So an undecided window's interval never reaches the radius, which
    every later layer would widen by ``|W|`` (on ResNet-18, ~10× a layer). Symbols in
    blocks stay in blocks (``kpstudy.verify.symbols.pool_chosen()``)."""

    makes_symbols = True
    keeps_blocks = True

    def forward(self, p, i, ins):
        l, u = ins[0].bounds()
        return self._pool(p, i, ins[0].mid, ins[0].rad, l, u)[0]

    def _pool(self, p, i, mid, rad, l, u, carried: bool = False):
        """Pool an input ``mid, rad`` bounded by ``l, u`` (``(B, C, H, W)``, its symbols'
        reach included). Returns the pooled value and, with ``carried`` (the zonotope:
        every window passes its chosen input, symbol rows of ``mid`` included), the
        undecided windows' excess ``μ (B, C, H_out, W_out)`` (0 where decided), already
        added to the constant row; without it, ``None``."""
        op = p.graph.nodes[i].op
        q = p.q
        B, rows, C, H, W = mid.shape
        lw, uw = _windows(op, l, float("-inf")), _windows(op, u, float("-inf"))  # (B, C, k, L)
        best = lw.argmax(2, keepdim=True)
        l_best = lw.gather(2, best)
        others = uw.scatter(2, best, float("-inf")).amax(2, keepdim=True)
        decided = (l_best >= others)[:, :, 0]  # (B, C, L)
        l_best = l_best[:, :, 0]
        u_max = uw.amax(2)
        Ho, Wo = _out_size(op, H, W)

        def pick(x):
            r = x.shape[1]
            win = _windows(op, x.reshape(B * r, C, H, W), 0.0).reshape(B, r, C, -1, Ho * Wo)
            return win.gather(3, best[:, None].expand(B, r, C, 1, Ho * Wo))[:, :, :, 0]

        zero = torch.zeros((), dtype=mid.dtype)
        excess = None
        if not carried:  # no symbols: keep the chosen input's lower bound linear in θ
            low, up = pick(mid - rad), torch.where(decided[:, None], pick(mid + rad), zero)
            up[:, 0] += torch.where(decided, zero, u_max)
            new_mid, new_rad = (up + low) / 2, (up - low) / 2
        else:
            new_mid, new_rad = pick(mid), pick(rad)
            excess = torch.where(decided, zero, (others[:, :, 0] - l_best).clamp_min(0) / 2)
            new_mid[:, 0] += excess
            excess = excess.reshape(B, C, Ho, Wo)
        p.saved[i] = (best[:, :, 0], decided, torch.where(decided, zero, u_max), (H, W))
        out_mid, out_rad = new_mid.reshape(B, rows, C, Ho, Wo), new_rad.reshape(B, q, C, Ho, Wo)
        return Region(out_mid, out_rad, p.domain), excess

    def zonotope(self, p, i, ins):
        x = ins[0]
        l, u = x.bounds()
        dense = x.blocks is None
        mid = _pad_rows(x.mid, p.made) if dense else x.mid  # new symbols come after all
        value, excess = self._pool(p, i, mid, x.rad, l, u, carried=True)
        kept = _budgeted(p, i, excess)
        value.rad[:, 0] += excess - kept  # the rest: radius
        new = symbols.make(kept, p.made)
        made = p.made + sum(b.rows for b in new)
        if dense:
            value = Region(symbols.dense(value.mid, new, made), value.rad, p.domain)
        else:
            op, shape = p.graph.nodes[i].op, p.graph.nodes[i].shape
            best = p.saved[i][0]  # (B, C, L)
            B, C, (Ho, Wo) = best.shape[0], best.shape[1], shape[1:]
            kw, (sh, sw), (ph, pw) = op.kernel[1], op.stride, op.padding
            row = (torch.arange(Ho) * sh - ph)[:, None] + best.view(B, C, Ho, Wo) // kw
            col = (torch.arange(Wo) * sw - pw) + best.view(B, C, Ho, Wo) % kw
            blocks = symbols.pool_chosen(op, x.blocks, row, col, shape) + new
            value = Region(value.mid, value.rad, p.domain, blocks)
        p.made = made
        return value

    def backward(self, graph, i, a, saved):
        """Lower ``y ≥ x[best]``; upper ``y ≤ x[best]`` where decided, else ``y ≤ max u``."""
        op = graph.nodes[i].op
        best, decided, u_const, (H, W) = saved
        B, r, C = a.shape[:3]
        a = a.flatten(3)  # (B, r, C, L)
        a_pos, a_neg = a.clamp_min(0), a.clamp_max(0)
        coef = a_pos + a_neg * decided[:, None]
        const = (a_neg * u_const[:, None]).flatten(2).sum(-1)
        # Input position of each window's chosen element, in the padded frame.
        kw, (sh, sw), (ph, pw) = op.kernel[1], op.stride, op.padding
        Ho, Wo = _out_size(op, H, W)
        oy, ox = torch.meshgrid(torch.arange(Ho), torch.arange(Wo), indexing="ij")
        iy = oy.reshape(-1) * sh + best // kw - ph
        ix = ox.reshape(-1) * sw + best % kw - pw
        flat = (iy * W + ix).clamp(0, H * W - 1)  # padding is never the chosen (−inf) element
        grad = torch.zeros(B, r, C, H * W, dtype=a.dtype)
        grad.scatter_add_(3, flat[:, None].expand(B, r, C, -1), coef)
        return [grad.reshape(B, r, C, H, W)], const


#: Operator kind (:attr:`kpstudy.verify.ops.Op.kind`) → its bound rules.
RULES: dict[str, Rules] = {"affine": AffineRules(), "relu": ReLURules(), "maxpool": MaxPoolRules()}


def rules(kind: str) -> Rules:
    """The bound rules of operator ``kind``; a ValueError naming it if none are registered."""
    try:
        return RULES[kind]
    except KeyError:
        raise ValueError(f"operator kind {kind!r} has no bound rules (operators.RULES)") from None


def _budgeted(p: Pass, i: int, mu: torch.Tensor) -> torch.Tensor:
    """``mu (B, *S)`` (new symbols' coefficients, ≥ 0) with all but the ``k`` largest
    entries of each region zeroed, ``k`` the symbols node ``i`` may make
    (:meth:`Pass.allow`)."""
    flat = mu.reshape(mu.shape[0], -1)
    most = int((flat > 0).sum(1).max())
    k = p.allow(i, most)
    if k >= most:
        return mu
    kept = torch.zeros_like(flat)
    if k > 0:
        top = flat.topk(k, 1)
        kept = kept.scatter(1, top.indices, top.values)
    return kept.view_as(mu)


def _windows(op: ops.MaxPool, x, fill: float):
    """``x (N, C, H, W)`` → windows ``(N, C, k_h·k_w, H_out·W_out)``, padding = ``fill``."""
    ph, pw = op.padding
    x = F.pad(x, (pw, pw, ph, ph), value=fill)
    N, C = x.shape[:2]
    cols = F.unfold(x, op.kernel, stride=op.stride)
    return cols.reshape(N, C, op.kernel[0] * op.kernel[1], -1)


def _out_size(op: ops.MaxPool, h: int, w: int) -> tuple[int, int]:
    (kh, kw), (sh, sw), (ph, pw) = op.kernel, op.stride, op.padding
    return (h + 2 * ph - kh) // sh + 1, (w + 2 * pw - kw) // sw + 1


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
