"""The branch-and-bound loop shared by :func:`~kpstudy.verify.bab.verify` and
:func:`~kpstudy.verify.reachable.reachable_argmax`.

A *node* is a row of a node tensor (a sub-simplex, sub-cube or sub-box of the input set's
parameter domain, :mod:`kpstudy.verify.sets`) with a *state* saying what is still open in
it: for :func:`verify` the groups not yet proved, ``(G,)`` bool; for
:func:`reachable_argmax` the indices not yet excluded, ``(G, S)`` bool. The loop is
breadth first: it takes up to ``batch`` nodes from the front of the queue, a ``decide``
function bounds them and says which stay open, and the open ones are split in two, each
child inheriting its parent's state. What a node decides is the caller's; the order of
the nodes, the budgets and the split are the loop's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from kpstudy import _checks
from kpstudy.verify.bounds import BoundsTimeout, zonotope_elements


class Step(NamedTuple):
    """What ``decide`` made of a batch of ``B`` nodes."""

    #: ``(B, …)``: each node's state after the batch (what its children inherit).
    state: torch.Tensor
    #: ``(B,)`` bool: the nodes to split.
    open: torch.Tensor
    #: End the search now; the open nodes stay in the queue, unsplit.
    stop: bool = False
    #: Whether the batch was bounded (and counts against ``max_nodes``).
    bounded: bool = True


@dataclass
class Search:
    """Outcome of :func:`branch_and_bound`."""

    #: ``(nodes, state, level)`` entries still open, in queue order.
    left: list
    #: Nodes bounded.
    nodes: int
    #: Deepest level taken from the queue (the root's level if none was).
    depth: int
    #: Why the loop ended: None (queue empty), ``'nodes'`` (``max_nodes`` spent),
    #: ``'time'`` (``deadline`` passed, between batches or inside ``decide``) or
    #: ``'stop'`` (``decide`` asked).
    stopped: str | None


def branch_and_bound(
    root: torch.Tensor,
    state: torch.Tensor,
    decide: Callable[[torch.Tensor, torch.Tensor, int], Step],
    split: Callable[[torch.Tensor], torch.Tensor],
    *,
    batch: int,
    deadline: float,
    max_nodes: int | None = None,
    exact_budget: bool = False,
    level: int = 0,
    queue: list | None = None,
) -> Search:
    """Breadth-first branch and bound from the nodes ``root`` with states ``state``.

    Parameters
    ----------
    root : Tensor, shape (R, …), or None
        The first nodes (the input set's root, or its first splits).
    state : Tensor, shape (R, …), or None
        Their states.
    decide : callable
        ``decide(nodes (B, …), state (B, …), level) -> Step``; it may raise
        :class:`~kpstudy.verify.bounds.BoundsTimeout`, and the batch then stays open with
        the states it came with.
    split : callable
        ``split(nodes (B, …)) -> (2B, …)``: the first halves of all nodes, then the second
        halves (the input set's ``split``).
    batch : int
        Most nodes per ``decide`` call.
    deadline : float
        ``time.perf_counter()`` value after which no further batch is taken.
    max_nodes : int, optional
        No further batch is taken once this many nodes are bounded. A batch may pass it,
        unless ``exact_budget``, where batches are cut to what the budget has left.
    level : int
        The root's depth (how often it was split).
    queue : list, optional
        ``(nodes, state, level)`` entries to start from instead of ``root``, ``state`` and
        ``level`` (None then): a search resumed where another stopped (its
        :attr:`Search.left`).

    Returns
    -------
    Search
    """
    queue = [(root, state, level)] if queue is None else list(queue)
    depth = min((entry[2] for entry in queue), default=level)
    done, stopped = 0, None
    while queue:
        if max_nodes is not None and done >= max_nodes:
            stopped = "nodes"
            break
        if time.perf_counter() > deadline:
            stopped = "time"
            break
        room = batch if max_nodes is None or not exact_budget else min(batch, max_nodes - done)
        nodes, state, level = _take(queue, room)
        depth = max(depth, level)
        try:
            step = decide(nodes, state, level)
        except BoundsTimeout:
            queue.insert(0, (nodes, state, level))
            stopped = "time"
            break
        done += len(nodes) if step.bounded else 0
        keep = step.open
        if step.stop:
            queue.insert(0, (nodes[keep], step.state[keep], level))
            stopped = "stop"
            break
        if keep.any():
            children = step.state[keep].repeat(2, *[1] * (step.state.ndim - 1))
            queue.append((split(nodes[keep]), children, level + 1))
    return Search(queue, done, depth, stopped)


def default_batch(graph, input_set, zonotope: bool, memory: int, widest: int = 0) -> int:
    """Nodes bounded together: as many as keep twice the largest centre stack (its affine
    rows on the largest value, or ``widest`` elements per row if larger, and a zonotope's
    error symbols: :func:`~kpstudy.verify.bounds.zonotope_elements`) within ``memory``
    elements, at most 64."""
    rows = input_set.rows
    biggest = max(widest, *(math.prod(n.shape) for n in graph.nodes))
    held = rows * biggest
    if zonotope:
        held = max(held, zonotope_elements(graph, rows))
    return max(1, min(64, memory // (2 * held)))


def absolute_tol(graph, input_set, tol: float) -> float:
    """``tol · (1 + max |y(X0)|)``: a margin tolerance that scales with the outputs'
    magnitude at the set's first point, as float32 rounding does."""
    with torch.no_grad():
        y0 = graph.forward(input_set.example_input().to(graph.dtype))
    return tol * (1.0 + float(y0.abs().max()))


def check_budget(timeout, max_nodes, batch, *, least_nodes: int = 1) -> None:
    """Refuse a search budget that is not seconds > 0, an optional node count of at least
    ``least_nodes`` and an optional positive batch."""
    _checks.seconds(timeout, "timeout")
    _checks.integer(max_nodes, "max_nodes", minimum=least_nodes, optional=True)
    _checks.integer(batch, "batch", minimum=1, optional=True)


def _take(queue: list, batch: int):
    """Pop up to ``batch`` nodes from the front of the queue (breadth first): the nodes,
    their states and the shallowest level among them."""
    nodes, states, levels, count = [], [], [], 0
    while queue and count < batch:
        n, s, level = queue.pop(0)
        room = batch - count
        if len(n) > room:
            queue.insert(0, (n[room:], s[room:], level))
            n, s = n[:room], s[:room]
        nodes.append(n)
        states.append(s)
        levels.append(level)
        count += len(n)
    return torch.cat(nodes), torch.cat(states), min(levels)
