"""Branch and bound over the input set's parameter domain, with an attack at every node.

Breadth-first: the open nodes are bounded ``batch`` at a time; a keypoint group is
closed in a node when every one of its margin rows has a lower bound above ``tol`` (or
above zero when recomputed in float64); the concrete model is evaluated at every open
node's vertices and centroid and, where the bounds fail, projected gradient descent on
the worst margin looks for a counterexample inside the node; nodes still open are split
(longest edge bisection for a simplex, longest side for a cube, widest pixel for a box),
the two children exactly covering their parent. The loop is
``kpstudy.verify.search.branch_and_bound()``, shared with
:func:`~kpstudy.verify.reachable.reachable_argmax`; what a node decides is
``_Search.decide()``.
"""

from __future__ import annotations

import copy
import time
from functools import partial

import torch

from kpstudy.verify.bounds import METHODS, row_bounds
from kpstudy.verify.graph import trace
from kpstudy.verify.result import Counterexample, Result
from kpstudy.verify.search import (
    Step,
    absolute_tol,
    branch_and_bound,
    check_budget,
    default_batch,
)
from kpstudy.verify.spec import ArgmaxSpec


def verify(
    model,
    input_set,
    spec,
    *,
    method: str = "auto",
    timeout: float = 60.0,
    max_nodes: int | None = None,
    batch: int | None = None,
    tol: float = 1e-5,
    attack_steps: int = 3,
    stop_on_violation: bool = True,
    memory: int = 2**25,
) -> Result:
    """Prove or refute ``spec`` for every point of ``input_set``.

    Parameters
    ----------
    model : nn.Module
        Eval-mode network of the operators of ``kpstudy.verify.graph``; its flattened
        output has ``spec.n_outputs`` entries.
    input_set : ConvexHull, Parallelotope or Box
        Images in the model's dtype (else a ValueError naming ``input_set``).
    spec : ArgmaxSpec
    method : {'auto', 'ibp', 'forward', 'crown', 'zonotope'}
        Bounds at each node (:mod:`kpstudy.verify.bounds`). ``'auto'`` is ``'zonotope'``:
        a forward pass per unstable ReLU, but on a trained CNN the only one whose bounds
        stay near the sampled range (``'forward'`` is the cheapest that keeps the margins'
        dependence on λ, but grows ~10× per layer there; ``'crown'`` costs a backward
        pass per margin row).
    timeout : float
        Seconds before the search stops with ``'unknown'`` (checked between nodes and,
        inside a node's bounds, between layers).
    max_nodes : int, optional
        Node budget: no further batch of nodes is bounded once this many are (a batch
        may pass it; batches depend on sizes only, so the verdict does not depend on the
        machine's speed).
    batch : int, optional
        Nodes bounded together (default: as many as fit in ``memory`` elements, counting
        a zonotope's error symbols).
    tol : float
        Margin lower bounds must exceed ``tol · (1 + max |y(X0)|)`` to close a group;
        those between zero and that are recomputed in float64 (for a float64 model,
        above zero suffices).
    attack_steps : int
        Projected-gradient steps per open node (eight times as many at the root).
    stop_on_violation : bool
        Stop at the first counterexample (other open groups stay ``'unknown'``).
    memory : int
        Element budget of the largest bound tensor.

    Returns
    -------
    Result

    Examples
    --------
    Outputs ``y = (x, 1/2)`` of a scalar image ``x``: index 0 stays the argmax on the hull
    of the images 1 and 2, not on that of 0 and 2.

    >>> from torch import nn
    >>> from kpstudy.verify import ConvexHull
    >>> net = nn.Sequential(nn.Linear(1, 2)).double().eval()
    >>> with torch.no_grad():
    ...     _ = net[0].weight.copy_(torch.tensor([[1.0], [0.0]]))
    ...     _ = net[0].bias.copy_(torch.tensor([0.0, 0.5]))
    >>> spec = ArgmaxSpec([2], [0])
    >>> result = verify(net, ConvexHull(torch.tensor([[1.0], [2.0]]).double()), spec)
    >>> result.status, result.nodes
    ('holds', 1)
    >>> result = verify(net, ConvexHull(torch.tensor([[0.0], [2.0]]).double()), spec)
    >>> result.status, result.counterexample.image
    ('violated', tensor([0.], dtype=torch.float64))
    """
    start = time.perf_counter()
    method = check_verify(method, timeout, max_nodes, batch)
    if not tol >= 0:
        raise ValueError(f"tol: expected a number >= 0, got {tol!r}")
    if not isinstance(spec, ArgmaxSpec):
        raise ValueError(f"spec: expected an ArgmaxSpec, got {type(spec).__name__}")
    _check_dtype(model, input_set)
    graph = trace(model, input_set.example_input())
    spec.check_output(graph.output_size)
    search = _Search(model, graph, input_set, spec, method, tol, memory, start + timeout)
    if batch is None:
        batch = default_batch(graph, input_set, method == "zonotope", memory)
    G = spec.n_groups
    open_groups = torch.zeros(G, dtype=torch.bool)
    open_groups[spec.active_groups] = True
    with torch.no_grad():
        done = branch_and_bound(
            input_set.root(),
            open_groups[None],
            partial(search.decide, attack_steps=attack_steps, stop=stop_on_violation),
            input_set.split,
            batch=batch,
            deadline=start + timeout,
            max_nodes=max_nodes,
        )
    still_open = torch.zeros(G, dtype=torch.bool)
    for _, m, _ in done.left:
        still_open |= m.any(0)
    violated = search.violated
    group_status = []
    for g in range(G):
        if spec.targets[g] is None:
            group_status.append("excluded")
        elif violated[g]:
            group_status.append("violated")
        elif still_open[g]:
            group_status.append("unknown")
        else:
            group_status.append("holds")
    if violated.any():
        status = "violated"
    elif still_open.any():
        status = "unknown"
    else:
        status = "holds"
    stats = {
        "method": method,
        "depth": done.depth,
        "batch": batch,
        "timed_out": done.stopped in ("nodes", "time"),
        "stopped": done.stopped,
        "float64_rechecks": search.rechecks,
        "root_margin": None if search.root_margin is None else search.root_margin.tolist(),
        "attack_margin": search.attack_margin.tolist(),
    }
    return Result(
        status, group_status, search.counterexample, time.perf_counter() - start, done.nodes, stats
    )


def check_verify(method, timeout, max_nodes, batch=None) -> str:
    """Raise ``ValueError`` naming the first of :func:`verify`'s bound method and budget
    arguments that is not valid (before any work); the method (``'auto'``: the zonotope)."""
    if method == "auto":
        method = "zonotope"
    if method not in METHODS:
        raise ValueError(f"method: expected 'auto' or one of {METHODS}, got {method!r}")
    check_budget(timeout, max_nodes, batch)
    return method


def _check_dtype(model, input_set) -> None:
    """A ValueError naming ``input_set`` when its images' dtype is not the model's (the
    dtype of its first parameter): the bounds run in the model's precision."""
    model_dtype = next((p.dtype for p in model.parameters()), None)
    set_dtype = getattr(input_set, "dtype", None)
    if model_dtype is not None and set_dtype is not None and set_dtype != model_dtype:
        name = str(model_dtype).removeprefix("torch.")
        raise ValueError(
            f"input_set: expected images of the model's dtype {model_dtype}, got {set_dtype} "
            f"(build the set from images.to(torch.{name}), or convert the model)"
        )


class _Search:
    """Bounds and attacks for one instance, and what they found so far."""

    def __init__(self, model, graph, input_set, spec, method, tol, memory, deadline):
        self.model, self.graph, self.set, self.spec = model, graph, input_set, spec
        self.method, self.tol, self.memory, self.deadline = method, tol, memory, deadline
        self.graph64 = self.model64 = None
        self.rechecks = 0
        #: Per group, the smallest margin the model showed at a point tried inside the set.
        self.attack_margin = torch.full((spec.n_groups,), torch.inf, dtype=torch.float64)
        #: Groups with a counterexample ``(G,)``, the first one found, the root's margins.
        self.violated = torch.zeros(spec.n_groups, dtype=torch.bool)
        self.counterexample: Counterexample | None = None
        self.root_margin: torch.Tensor | None = None
        self.tol_abs = absolute_tol(graph, input_set, tol)

    def decide(self, nodes, mask, level: int, *, attack_steps: int, stop: bool) -> Step:
        """One batch of ``kpstudy.verify.search.branch_and_bound()``: the groups still
        open ``(B, G)`` in ``nodes`` after cheap falsification (corners and centroid),
        bounds, then ``attack_steps`` of gradient descent (eight times as many at the
        root) where the bounds fail. With ``stop``, the search stops at a counterexample
        (the batch counts as bounded only if its bounds were computed)."""
        self._record(self.probe(nodes, mask & ~self.violated))
        mask = mask & ~self.violated
        found = self.counterexample is not None and stop
        if not found:
            margin, proved = self.group_margins(nodes, mask)  # (B, G)
            if self.root_margin is None:
                self.root_margin = margin[0].clone()
            mask = mask & ~proved
            self._record(self.descend(nodes, mask, attack_steps * (8 if level == 0 else 1)))
            mask = mask & ~self.violated
        stopped = self.counterexample is not None and stop
        return Step(mask, mask.any(1), stop=stopped, bounded=not found)

    def _record(self, found: dict[int, Counterexample]) -> None:
        for g, cex in found.items():
            self.violated[g] = True
            self.counterexample = self.counterexample or cex

    def group_margins(self, nodes, mask) -> tuple[torch.Tensor, torch.Tensor]:
        """Lower bounds ``(B, G)`` of each open group's smallest margin (+inf if closed
        already), and whether each is proved: above ``tol``, or above zero in float64."""
        spec = self.spec
        rows = mask[:, spec.row_group].any(0)  # rows needed by some node of the batch
        region = self.set.region(nodes, self.graph.dtype)
        lower = torch.full((len(nodes), spec.n_rows), float("inf"), dtype=torch.float64)
        if not rows.any():  # single-cell groups only: nothing to bound
            margin = lower.new_full(mask.shape, torch.inf)
            return margin, margin > 0
        lower[:, rows] = row_bounds(
            self.graph,
            region,
            spec.row_pos[rows],
            spec.row_neg[rows],
            self.method,
            memory=self.memory,
            deadline=self.deadline,
        ).double()
        margin = torch.where(mask, spec.group_min(lower), torch.inf)
        if self.graph.dtype == torch.float64:
            return margin, margin > 0
        proved = margin > self.tol_abs
        close = (margin > 0) & ~proved
        if close.any():
            proved |= close & self._float64_proves(nodes, close)
        return margin, proved

    def _model64(self):
        """A float64 copy of the model (made once)."""
        if self.model64 is None:
            self.model64 = copy.deepcopy(self.model).double()
        return self.model64

    def _margins64(self, points) -> torch.Tensor:
        """Group margins ``(B, G)`` of the float64 model at the exact set points (float64)."""
        y = self._model64()(self.set.image(points, dtype=torch.float64)).flatten(1)
        return self.spec.group_min(self.spec.margins(y))

    def _float64_proves(self, nodes, close) -> torch.Tensor:
        """Whether float64 bounds prove the groups with a close call ``(B, G)``."""
        if self.graph64 is None:
            self.graph64 = trace(self._model64(), self.set.example_input().double())
        which = close.any(1)
        self.rechecks += int(which.sum())
        region = self.set.region(nodes[which], torch.float64)
        spec = self.spec
        lower = row_bounds(
            self.graph64,
            region,
            spec.row_pos,
            spec.row_neg,
            self.method,
            deadline=self.deadline,
        )
        out = torch.zeros(close.shape, dtype=torch.bool)
        out[which] = spec.group_min(lower) > 0
        return out

    # -- attack ------------------------------------------------------------------------
    def probe(self, nodes, mask) -> dict[int, Counterexample]:
        """Counterexamples for open groups at each node's corners and centroid."""
        open_nodes = mask.any(1)
        if not open_nodes.any():
            return {}
        nodes, mask = nodes[open_nodes], mask[open_nodes]
        points = self.set.node_points(nodes)  # (B, P, …)
        B, P = points.shape[:2]
        flat = points.reshape(B * P, *points.shape[2:])
        return self._recheck(flat, mask.repeat_interleave(P, 0))

    def descend(self, nodes, mask, steps: int) -> dict[int, Counterexample]:
        """Counterexamples for open groups by projected gradient descent on each open
        node's worst margin (re-checked)."""
        open_nodes = mask.any(1)
        if not open_nodes.any() or steps == 0:
            return {}
        nodes, mask = nodes[open_nodes], mask[open_nodes]
        return self._recheck(self._descend(nodes, mask, steps), mask)

    def _descend(self, nodes, mask, steps):
        """Projected gradient descent on each node's worst open margin; returns points."""
        w = self.set.centre_weights(nodes)
        rows = mask[:, self.spec.row_group]
        lr = 0.5
        for _ in range(steps):
            w = w.detach().requires_grad_(True)
            with torch.enable_grad():
                x = self.set.image(self.set.node_point(nodes, w))
                y = self.model(x).flatten(1)
                m = torch.where(rows, self.spec.margins(y).double(), torch.inf)
                worst = m.min(1).values
                (grad,) = torch.autograd.grad(worst.sum(), w)
            scale = grad.flatten(1).abs().amax(1).clamp_min(1e-30)
            step = grad / scale.reshape(-1, *([1] * (grad.ndim - 1)))
            w = w.detach() - lr * step
            w = self.set.project_weights(w)
            lr *= 0.7
        return self.set.node_point(nodes, w.detach())

    def _recheck(self, points, mask) -> dict[int, Counterexample]:
        """Counterexamples among ``points`` (set parameters): inside the set, and failing
        an open group on the concrete model at the set's exact point in float64.

        The model runs on the images in its own dtype first; the points whose margin
        there is at most ``tol`` for an open group are evaluated again on the exact set
        point (:meth:`image` in float64) by a float64 copy of the model, and only that
        margin counts: a point that fails only on its float32-rounded image is no
        counterexample, and its group stays open for the search."""
        points = self.set.clip(points)
        inside = self.set.contains_point(points)
        x = self.set.image(points)
        y = self.model(x).flatten(1)
        margin = self.spec.group_min(self.spec.margins(y).double())
        close = ((margin <= self.tol_abs) & mask & inside[:, None]).any(1)
        if close.any() and self.graph.dtype != torch.float64:
            margin[close] = self._margins64(points[close])
        if inside.any():
            seen = margin[inside].min(0).values
            self.attack_margin = torch.minimum(self.attack_margin, seen)
        bad = (margin <= 0) & mask & inside[:, None]
        found = {}
        for i, g in bad.nonzero().tolist():
            if g not in found:
                found[g] = Counterexample(points[i], x[i], g, float(margin[i, g]))
        return found
