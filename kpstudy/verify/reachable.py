"""Where can each group's argmax go? Sound reachable sets by branch and bound.

For a concatenated output (one group per keypoint, e.g. a keypoint's heatmap pixels) and
an input set, :func:`reachable_argmax` returns for every group a *possible* set of output
indices — a sound superset of the indices that are the argmax somewhere in the set — and
a *reached* set with a witness point for each of its indices.

Exclusion rule, per node of the branch and bound: index ``i`` is dropped when some
candidate ``c`` provably beats it everywhere in the node, ``min_θ (ℓ_c(θ) − u_i(θ)) > tol``
with ``ℓ``, ``u`` the linear lower and upper bounds of the outputs in the node's
parameters (:func:`kpstudy.verify.bounds.propagate`) and the minimum taken exactly over
the node's domain. The candidates are the ``candidates`` indices with the largest lower
bounds, so the rule is never weaker than comparing intervals. The union of the nodes'
undropped indices is the possible set. Witnesses come from the concrete model at the
set's corners, random points and every node's centre: the argmax there is reached. A
node is split while it keeps, for some group, an index not yet reached; the search ends
when the possible and reached sets agree (``complete``) or the budget is spent. The loop
is ``kpstudy.verify.search.branch_and_bound()``, shared with
:func:`~kpstudy.verify.bab.verify`.

With the zonotope on a network that is affine after its last ReLU, a node is first
bounded through that affine tail with its error symbols in the radius (cheap); it carries
its symbols through the tail only where those bounds leave an index without a witness
(``_Reach.undominated``). The sets and node counts are the same either way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from kpstudy import _checks
from kpstudy.verify import symbols
from kpstudy.verify.bounds import propagate
from kpstudy.verify.graph import trace
from kpstudy.verify.region import domain_min
from kpstudy.verify.search import (
    Step,
    absolute_tol,
    branch_and_bound,
    check_budget,
    default_batch,
)
from kpstudy.verify.sets import ConvexHull
from kpstudy.verify.symbols import l1_rows

METHODS = ("ibp", "forward", "zonotope")
#: Most root splits :func:`reachable_argmax` makes before bounding (2^12 nodes).
MAX_START_DEPTH = 12


@dataclass
class Frontier:
    """Where a :func:`reachable_argmax` search stopped: enough to resume it.

    Attributes
    ----------
    queue : list
        ``(nodes, state, level)`` entries not yet bounded, each node with the indices
        ``(B, G, S)`` its parent kept: the search's open nodes, and the children of nodes
        it closed only because they held no index of its ``focus`` without a witness.
    resolved : Tensor, shape (G, S), bool
        Indices kept by the nodes it closed with every kept index reached.
    """

    queue: list
    resolved: torch.Tensor


@dataclass
class Regions:
    """Outcome of :func:`reachable_argmax`.

    Attributes
    ----------
    group_sizes : list of int
    possible : list of ndarray
        Per group, sorted indices within the group that may be the argmax somewhere in the
        set (a sound superset: every other index is provably beaten everywhere).
    witnesses : list of dict
        Per group, ``{index: point}``: a set parameter (``λ (n,)``) at which the concrete
        model's argmax in that group is ``index``.
    time : float
        Seconds.
    nodes : int
        Branch-and-bound nodes bounded.
    stats : dict
        ``method``, ``depth``, ``candidates``; ``stopped``: ``'nodes'`` (``max_nodes``
        spent), ``'time'`` (``timeout`` fired; also ``timed_out``) or None (finished).
    frontier : Frontier, optional
        Where the search stopped (``resume`` of :func:`reachable_argmax`).
    """

    group_sizes: list[int]
    possible: list[np.ndarray]
    witnesses: list[dict[int, torch.Tensor]]
    time: float
    nodes: int
    stats: dict = field(default_factory=dict)
    frontier: Frontier | None = None

    def reached(self, group: int) -> np.ndarray:
        """Sorted indices of ``group`` with a witness (a subset of ``possible[group]``)."""
        return np.array(sorted(self.witnesses[group]), dtype=np.int64)

    @property
    def gap(self) -> np.ndarray:
        """Per group, possible indices without a witness ``(G,)``."""
        return np.array([len(p) - len(w) for p, w in zip(self.possible, self.witnesses)])

    @property
    def complete(self) -> bool:
        """Whether every possible index was reached: the sets are exact."""
        return not self.gap.any()


def reachable_argmax(
    model,
    input_set,
    group_sizes,
    *,
    method: str = "forward",
    timeout: float = 10.0,
    max_nodes: int | None = None,
    batch: int | None = None,
    start_depth: int = 0,
    candidates: int = 4,
    samples: int = 64,
    seed: int = 0,
    tol: float = 1e-5,
    memory: int = 2**25,
    focus=None,
    resume: Regions | None = None,
    witnesses=None,
    tail_first: bool = True,
) -> Regions:
    """Sound sets of the indices each output group's argmax can take over ``input_set``.

    Parameters
    ----------
    model : nn.Module
        Eval-mode network of the operators of ``kpstudy.verify.graph``; its flattened
        output is the concatenation of the groups.
    input_set : ConvexHull or Parallelotope
    group_sizes : sequence of int
        Entries per group, summing to the model's output size.
    method : {'forward', 'ibp', 'zonotope'}
        Bounds at each node (:mod:`kpstudy.verify.bounds`); with ``'zonotope'`` the error
        symbols shared by a candidate and an index cancel in their margin.
    timeout : float
        Seconds before the search stops (checked between nodes and, inside a node's
        bounds, between layers); the possible sets are sound at any time.
    max_nodes, batch : int, optional
        Most nodes to bound (0: witnesses only, every index stays possible); nodes bounded
        together (default: what fits in ``memory``).
    start_depth : int
        Splits of the root before the first bounds: the search starts from ``2^start_depth``
        nodes (for a simplex of ``n`` vertices after the seed, ``start_depth = k·n`` gives
        nodes of about ``2^-k`` of the set's size per direction). A set that is exact only
        on small nodes skips its costliest, undecisive bounds that way; the corners of the
        whole set are still evaluated for witnesses.
    candidates : int
        Indices per group (largest lower bounds) that try to beat each other index.
    samples : int
        Random points of the set evaluated at the start for witnesses.
    seed : int
    tol : float
        A candidate beats an index when its margin's lower bound exceeds
        ``tol · (1 + max |y(X0)|)`` (float32 rounding never drops a reachable index).
    memory : int
        Element budget of the largest bound tensor.
    focus : sequence of array_like of int, optional
        Per group, the indices worth a split: a node stays open only while it keeps one
        of them without a witness (default: every index). The possible sets stay sound;
        the budget goes to the nodes that hold the indices a caller needs removed.
    resume : Regions, optional
        A search of the same ``model``, ``input_set`` and groups to continue from its
        :class:`Frontier` (with its witnesses) instead of the root, typically with another
        ``focus``: no node is bounded twice, and ``max_nodes`` counts the new ones only.
        ``start_depth``, ``samples`` and ``seed`` are then unused.
    witnesses : sequence of dict, optional
        Per group, ``{index: λ (n,)}``: points at which the caller has already evaluated
        the concrete model and found that group's argmax at ``index`` (typically the
        images it sampled itself, passed with ``samples=0`` so that none is evaluated
        twice). They count as reached, before the search's own samples.
    tail_first : bool
        With ``'zonotope'`` on a network that is affine after its last ReLU, bound each
        node there first with its symbols in the radius, and carry them through the
        affine tail only where that leaves an index without a witness (module
        docstring). False carries every node's symbols through the whole network: the
        same sets and nodes, slower (a baseline).

    Returns
    -------
    Regions

    Examples
    --------
    One group ``y = (1 − x, x, 0.2)`` of a scalar image ``x`` on the hull of 0 and 1:
    index 0 wins below ``x = 1/2``, index 1 above, index 2 nowhere.

    >>> from torch import nn
    >>> from kpstudy.verify import ConvexHull
    >>> net = nn.Sequential(nn.Linear(1, 3)).double().eval()
    >>> with torch.no_grad():
    ...     _ = net[0].weight.copy_(torch.tensor([[-1.0], [1.0], [0.0]]))
    ...     _ = net[0].bias.copy_(torch.tensor([1.0, 0.0, 0.2]))
    >>> regions = reachable_argmax(net, ConvexHull(torch.tensor([[0.0], [1.0]]).double()), [3])
    >>> regions.possible[0], regions.complete
    (array([0, 1]), True)
    """
    start = time.perf_counter()
    check_search(method, timeout, max_nodes, start_depth, batch)
    if not isinstance(input_set, ConvexHull):  # or a Parallelotope: points are λ
        raise ValueError(
            f"input_set: expected a ConvexHull or Parallelotope, got {type(input_set).__name__}"
        )
    _checks.integer(candidates, "candidates", minimum=1)
    _checks.integer(samples, "samples", minimum=0)
    sizes = [int(s) for s in group_sizes]
    if not sizes or min(sizes) < 1:
        raise ValueError(f"group_sizes: expected integers >= 1, got {list(group_sizes)!r}")
    if witnesses is not None:
        check_witnesses(witnesses, sizes, input_set.n)
    graph = trace(model, input_set.example_input())
    if graph.output_size != sum(sizes):
        raise ValueError(
            f"group_sizes: expected them to sum to the model's {graph.output_size} outputs, "
            f"got {sum(sizes)}"
        )
    G, S = len(sizes), max(sizes)
    search = _Reach(
        model, graph, input_set, sizes, method, min(candidates, S), tol, start + timeout
    )
    if not tail_first:
        search.tail = None
    if focus is not None:
        if len(focus) != G:
            raise ValueError(f"focus: expected {G} index arrays (one per group), got {len(focus)}")
        search.focus = torch.zeros(G, S, dtype=torch.bool)
        for g, indices in enumerate(focus):
            indices = np.asarray(indices, dtype=np.int64).reshape(-1)
            if indices.size and (indices.min() < 0 or indices.max() >= sizes[g]):
                raise ValueError(f"focus: group {g}'s indices must lie in [0, {sizes[g]})")
            search.focus[g, torch.from_numpy(indices)] = True
    if batch is None:
        widest = G * S * (candidates + 2)
        batch = default_batch(graph, input_set, method == "zonotope", memory, widest)

    with torch.no_grad():
        if resume is not None:
            queue = search.resume(resume)
        if witnesses is not None:
            search.take_witnesses(witnesses)
        if resume is None:
            if samples:
                search.witness(input_set.sample(samples, seed))
            root = input_set.root()
            search.witness(input_set.node_points(root).reshape(-1, input_set.n))  # corners
            for _ in range(start_depth):
                root = input_set.split(root)
            queue = [(root, search.valid[None].repeat(len(root), 1, 1), start_depth)]
        done = branch_and_bound(
            None,
            None,
            search.decide,
            input_set.split,
            batch=batch,
            deadline=start + timeout,
            max_nodes=max_nodes,
            exact_budget=True,
            queue=queue,
        )
        possible = search.possible.clone()
        for _, parent, _ in done.left:  # what was left open keeps its parent's sets
            possible |= parent.any(0)
        possible |= search.reached  # float rounding must never drop a witnessed index
        parked = [(input_set.split(n), s.repeat(2, 1, 1), lv + 1) for n, s, lv in search.parked]
    return Regions(
        sizes,
        [np.flatnonzero(p.numpy()) for p in possible],
        search.witnesses,
        time.perf_counter() - start,
        done.nodes,
        {
            "method": method,
            "depth": done.depth,
            "timed_out": done.stopped == "time",
            "stopped": done.stopped,
            "candidates": candidates,
        },
        Frontier(done.left + search.carried + parked, search.resolved.clone()),
    )


def check_witnesses(witnesses, sizes, n: int) -> None:
    """Raise ``ValueError`` unless ``witnesses`` holds, per group of ``sizes``, a dict of
    indices within the group to points ``λ (n,)``."""
    if len(witnesses) != len(sizes):
        raise ValueError(
            f"witnesses: expected {len(sizes)} dicts (one per group), got {len(witnesses)}"
        )
    for g, found in enumerate(witnesses):
        for i, lam in found.items():
            if not 0 <= int(i) < sizes[g]:
                raise ValueError(f"witnesses: group {g}'s indices must lie in [0, {sizes[g]})")
            if tuple(torch.as_tensor(lam).shape) != (n,):
                raise ValueError(f"witnesses: expected points λ of shape ({n},)")


def check_search(method, timeout, max_nodes, start_depth, batch=None) -> None:
    """Raise ``ValueError`` naming the first of :func:`reachable_argmax`'s search
    arguments that is not valid (before any work)."""
    _checks.choice(method, "method", METHODS)
    check_budget(timeout, max_nodes, batch, least_nodes=0)  # 0: witnesses only
    _checks.integer(start_depth, "start_depth", minimum=0, maximum=MAX_START_DEPTH)


class _Reach:
    """Bounds and witnesses for one reachability search."""

    def __init__(self, model, graph, input_set, sizes, method, candidates, tol, deadline):
        self.model, self.graph, self.set, self.deadline = model, graph, input_set, deadline
        self.G, self.S, self.method, self.k = len(sizes), max(sizes), method, candidates
        self.sizes = list(sizes)
        # Groups padded to a (G, S) layout: flat output index and whether it exists.
        offsets = np.cumsum([0, *sizes[:-1]])
        within = torch.arange(self.S)
        self.valid = within[None] < torch.tensor(sizes)[:, None]
        self.flat = torch.where(self.valid, torch.tensor(offsets)[:, None] + within, 0)
        self.uniform = bool(self.valid.all())  # equal groups: the layout is a view
        self.reached = torch.zeros(self.G, self.S, dtype=torch.bool)
        self.focus = self.valid.clone()  # indices whose lack of a witness keeps a node open
        #: Indices undominated in some node closed so far ``(G, S)``.
        self.possible = torch.zeros(self.G, self.S, dtype=torch.bool)
        #: Of those, the ones of nodes closed with every kept index reached.
        self.resolved = torch.zeros(self.G, self.S, dtype=torch.bool)
        #: ``(nodes, kept, level)`` closed for want of a focus index, bounded / unbounded.
        self.parked: list = []
        self.carried: list = []
        self.witnesses: list[dict[int, torch.Tensor]] = [{} for _ in sizes]
        self.tol_abs = absolute_tol(graph, input_set, tol)
        #: ``(head, tail)`` of a zonotope search on a graph with an affine tail, else None.
        self.tail = graph.split_affine_tail() if method == "zonotope" else None

    def resume(self, regions: Regions) -> list:
        """Take over ``regions``' witnesses and :class:`Frontier`; the frontier's entries
        that keep a focus index without a witness, to bound (the others stay in the
        frontier, their indices possible)."""
        if regions.frontier is None or list(regions.group_sizes) != self.sizes:
            raise ValueError(
                f"resume: expected the Regions of a search over groups {self.sizes} "
                "(with its frontier)"
            )
        for g, found in enumerate(regions.witnesses):
            self.witnesses[g] = dict(found)
            self.reached[g, list(found)] = True
        self.resolved = regions.frontier.resolved.clone()
        self.possible = self.resolved.clone()
        queue = []
        for nodes, state, level in regions.frontier.queue:
            open_ = (state & ~self.reached & self.focus).flatten(1).any(1)
            if (~open_).any():
                self.possible |= state[~open_].any(0)
                self.carried.append((nodes[~open_], state[~open_], level))
            if open_.any():
                queue.append((nodes[open_], state[open_], level))
        return queue

    def take_witnesses(self, witnesses) -> None:
        """Record a caller's ``{index: λ}`` per group (:func:`check_witnesses`) as reached."""
        for g, found in enumerate(witnesses):
            for i, lam in found.items():
                if not self.reached[g, int(i)]:
                    self.reached[g, int(i)] = True
                    self.witnesses[g][int(i)] = torch.as_tensor(lam, dtype=torch.float64).clone()

    def witness(self, points: torch.Tensor) -> None:
        """Record the concrete argmax of every group at ``points (P, n)``."""
        for chunk in points.split(64):
            y = self._padded(self.model(self.set.image(chunk)).flatten(1), float("-inf"))
            best = y.argmax(-1)  # (P, G): the first of tied maxima, as torch.argmax
            for p, g in (~self.reached.gather(1, best.T).T).nonzero().tolist():
                i = int(best[p, g])
                if not self.reached[g, i]:
                    self.reached[g, i] = True
                    self.witnesses[g][i] = chunk[p].clone()

    def decide(self, nodes, parent, level: int) -> Step:
        """One batch of ``kpstudy.verify.search.branch_and_bound()``: witnesses at the
        nodes' centres, then the indices still possible ``(B, G, S)`` in each node (those
        of its ``parent`` not provably beaten); a node stays open while it keeps an index
        of :attr:`focus` without a witness, and a closed node's indices join
        :attr:`possible`."""
        self.witness(self.set.node_points(nodes)[:, -1])  # the centres
        kept = self.undominated(nodes, parent)
        unreached = kept & ~self.reached
        open_ = (unreached & self.focus).flatten(1).any(1)
        parked = ~open_ & unreached.flatten(1).any(1)  # open but for the focus
        self.possible |= kept[~open_].any(0)
        self.resolved |= kept[~open_ & ~parked].any(0)
        if parked.any():
            self.parked.append((nodes[parked], kept[parked], level))
        return Step(kept, open_)

    def undominated(self, nodes: torch.Tensor, parent: torch.Tensor) -> torch.Tensor:
        """Indices of ``parent (B, G, S)`` not provably beaten in each node, ``(B, G, S)``
        bool.

        A zonotope whose output is an affine map of the last ReLU (the patch decoder) is
        bounded there first with its symbols in the radius: a node where that leaves no
        index without a witness is closed on those bounds (the indices it keeps are
        reached, so the possible sets are the same), and only the others carry their
        symbols through the tail to the exact test."""
        region = self.set.region(nodes, self.graph.dtype)
        if self.method == "ibp":
            region = region.to_interval()
        zonotope = self.method == "zonotope"
        if not zonotope or self.tail is None:
            out, _ = propagate(
                self.graph, region, zonotope=zonotope, deadline=self.deadline, dense=False
            )
            return self._exact(out) & parent
        head, tail = self.tail
        inner, _ = propagate(head, region, zonotope=True, deadline=self.deadline, dense=False)
        loose, _ = propagate(tail, inner.without_symbols())
        lower, upper = loose.bounds()
        lower = self._padded(lower.flatten(1), float("-inf"))
        upper = self._padded(upper.flatten(1), 0.0)
        best = lower.amax(-1, keepdim=True)
        kept = ~(best > upper + self.tol_abs) & self.valid & parent
        open_ = kept & ~self.reached
        exact = open_.flatten(1).any(1)
        if not exact.any():
            return kept
        inner = inner.select(exact)
        groups = open_[exact].any(0).any(-1).nonzero().flatten()  # the groups worth it
        narrow = self._channels(tail, groups) if len(groups) < self.G else None
        if narrow is None:
            out, _ = propagate(tail, inner, zonotope=True, dense=False)
            kept[exact] = self._exact(out) & parent[exact]
        else:
            out, _ = propagate(narrow, inner, zonotope=True, dense=False)
            rows = exact.nonzero()
            kept[rows, groups] = self._exact(out, groups) & parent[rows, groups]
        return kept

    def _channels(self, tail, groups: torch.Tensor):
        """``tail`` computing groups ``groups`` alone where each group is one channel of
        its ``(C, H, W)`` output (a heatmap per keypoint), else None."""
        shape = tail.nodes[-1].shape
        if not self.uniform or len(shape) != 3 or tuple(shape[:1]) != (self.G,):
            return None
        return tail.output_channels(groups)

    def _exact(self, out, groups: torch.Tensor | None = None) -> torch.Tensor:
        """Indices not provably beaten, ``(B, G, S)`` bool, from the output's bounds;
        ``(B, len(groups), S)`` from an output of those (equal-sized) groups alone."""
        if groups is None:
            valid, flat, padded = self.valid, self.flat, self._padded
        else:
            valid = self.valid[groups]
            flat = torch.arange(valid.numel()).view(valid.shape)

            def padded(y, fill):
                return y.unflatten(-1, valid.shape)

        q = out.rad.shape[1]  # rows of the affine part in θ; the symbols follow
        mid, rad = out.mid[:, :q].flatten(2), out.rad.flatten(2)
        low = padded(mid - rad, float("-inf"))  # a missing entry never beats
        up = padded(mid + rad, 0.0)
        reach = out.reach()
        spread = padded(reach.flatten(1), 0.0) if torch.is_tensor(reach) else reach
        lower = domain_min(low, out.domain) - spread  # (B, G, S)
        upper = -domain_min(-up, out.domain) + spread
        top = lower.topk(self.k, dim=-1).indices  # (B, G, k)
        # Intervals first (ℓ_c ≥ lower_c > upper_i), then, for what they leave, the
        # linear bounds: min over θ of ℓ_c(θ) − u_i(θ), less the symbols' share.
        beaten = (lower.gather(2, top).amax(-1, keepdim=True) > upper + self.tol_abs) & valid
        # One group at a time, over the indices the intervals leave and the candidates:
        # their symbols alone are read (a dense stack of every output's symbols can be
        # ten times the pass that made it); with the symbols in blocks and a heatmap per
        # group, only those that reach the candidate (symbols.overlap).
        hw = out.mid.shape[-2:]
        windowed = (
            bool(out.blocks)
            and out.mid.dim() == 5
            and out.mid.shape[2] == valid.shape[0]
            and hw[0] * hw[1] == valid.shape[1]
            and bool(valid.all())
        )
        for g in (~beaten & valid).any(0).any(-1).nonzero().flatten().tolist():
            left = ((~beaten[:, g]) & valid[g]).any(0).nonzero().flatten()  # (L,)
            if windowed:
                self._margins_by_overlap(out, g, left, low, up, spread, top, beaten)
                continue
            tops, slot = top[:, g].unique(return_inverse=True)  # (U,), (B, k)
            coeff = out.symbols_at(flat[g, torch.cat([left, tops])])  # (B, E, L + U)
            symbols_g, picks = coeff[..., : len(left)], coeff[..., len(left) :]
            up_g = up[:, :, g, left]  # (B, q, L)
            for c in range(self.k):
                at = top[:, g, c].view(-1, 1, 1)  # (B, 1, 1)
                margin = domain_min(
                    low[:, :, g].gather(2, at.expand(-1, low.shape[1], 1)) - up_g, out.domain
                )
                pick = picks.gather(2, slot[:, c].view(-1, 1, 1).expand(-1, picks.shape[1], 1))
                share = l1_rows(symbols_g - pick)  # (B, L)
                beaten[:, g, left] |= margin - share > self.tol_abs
        return ~beaten & valid

    def _margins_by_overlap(self, out, g, left, low, up, spread, top, beaten) -> None:
        """``_exact``'s linear test of group ``g`` (channel ``g`` of a ``(G, H, W)`` output
        whose symbols are in blocks) on indices ``left``: the symbols' share of each
        margin from their reach and :func:`~kpstudy.verify.symbols.overlap`."""
        W = out.mid.shape[-1]
        up_g = up[:, :, g, left]  # (B, q, L)
        for c in range(self.k):
            at = top[:, g, c]  # (B,)
            margin = domain_min(
                low[:, :, g].gather(2, at.view(-1, 1, 1).expand(-1, low.shape[1], 1)) - up_g,
                out.domain,
            )
            shared = symbols.overlap(out.blocks, g, at // W, at % W, out.mid.shape[-2:])
            reach = spread[:, g, left].double() + spread[:, g].gather(1, at[:, None]).double()
            beaten[:, g, left] |= margin - (reach - shared[:, left]) > self.tol_abs

    def _padded(self, y: torch.Tensor, fill: float) -> torch.Tensor:
        """``y (..., N)`` flat outputs → ``(..., G, S)``, ``fill`` where a group is short."""
        if self.uniform:  # no copy of the (B, E, N) symbol stack
            return y.unflatten(-1, (self.G, self.S))
        return torch.where(self.valid, y[..., self.flat], fill)


__all__ = ["Frontier", "Regions", "reachable_argmax"]
