"""kpstudy.verify.search: the branch-and-bound loop (order, budgets, stopping and resuming),
the default node batch, the absolute margin tolerance and the budget's checks."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.verify import ConvexHull
from kpstudy.verify.graph import trace
from kpstudy.verify.search import (
    Step,
    absolute_tol,
    branch_and_bound,
    check_budget,
    default_batch,
)


def test_the_search_loop_is_breadth_first_within_its_budgets():
    """The loop shared with reachable_argmax, on intervals of [0, 1] that stay open while
    wider than 1/4: batches cross levels in queue order (first halves first), a node
    budget is passed by at most a batch unless exact, and a batch that ``decide`` stops at
    or that times out stays in the queue unsplit."""
    from kpstudy.verify.bounds import BoundsTimeout

    seen = []

    def decide(nodes, state, level):
        seen.append(nodes[:, 0].tolist())
        return Step(state, nodes[:, 1] - nodes[:, 0] > 0.25)

    def halve(nodes):
        mid = nodes.mean(1)
        return torch.cat([torch.stack([nodes[:, 0], mid], 1), torch.stack([mid, nodes[:, 1]], 1)])

    root, state = torch.tensor([[0.0, 1.0]]), torch.ones(1, 1, dtype=torch.bool)
    done = branch_and_bound(root, state, decide, halve, batch=3, deadline=float("inf"))
    assert seen == [[0.0], [0.0, 0.5], [0.0, 0.5, 0.25], [0.75]]
    assert (done.nodes, done.depth, done.stopped, done.left) == (7, 2, None, [])
    for exact, nodes, left in ((False, 6, 1), (True, 4, 3)):
        done = branch_and_bound(
            root,
            state,
            decide,
            halve,
            batch=3,
            deadline=float("inf"),
            max_nodes=4,
            exact_budget=exact,
        )
        assert (done.nodes, done.stopped) == (nodes, "nodes")
        assert sum(len(n) for n, _, _ in done.left) == left

    def stop_at_level_1(nodes, state, level):
        return Step(state & False, (nodes[:, 0] > 0.1) | (level == 0), stop=level == 1)

    done = branch_and_bound(root, state, stop_at_level_1, halve, batch=3, deadline=float("inf"))
    ((nodes, kept, level),) = done.left
    assert (done.nodes, done.stopped, level, nodes.tolist()) == (3, "stop", 1, [[0.5, 1.0]])
    assert not kept.any()  # the state decide returned, unsplit

    def time_out_below_the_root(nodes, state, level):
        if level > 0:
            raise BoundsTimeout
        return Step(state & False, torch.tensor([True]))

    done = branch_and_bound(root, state, time_out_below_the_root, halve, batch=3, deadline=1e300)
    ((nodes, kept, level),) = done.left
    assert (done.nodes, done.stopped, level, len(nodes)) == (1, "time", 1, 2)
    assert not kept.any()  # the states the batch came with: its parent's


def _halve(nodes):
    mid = nodes.mean(1)
    return torch.cat([torch.stack([nodes[:, 0], mid], 1), torch.stack([mid, nodes[:, 1]], 1)])


def _wider_than_a_quarter(seen):
    def decide(nodes, state, level):
        seen.append((level, nodes[:, 0].tolist()))
        return Step(state, nodes[:, 1] - nodes[:, 0] > 0.25)

    return decide


def test_a_search_resumed_from_its_queue_goes_on_as_one_longer_search():
    """A search stopped by its node budget and resumed from ``left`` bounds the same nodes
    in the same order as one search; a deadline already passed bounds nothing and leaves
    the root in the queue."""
    root, state = torch.tensor([[0.0, 1.0]]), torch.ones(1, 1, dtype=torch.bool)
    whole, parts = [], []
    once = branch_and_bound(
        root, state, _wider_than_a_quarter(whole), _halve, batch=2, deadline=float("inf")
    )
    first = branch_and_bound(
        root,
        state,
        _wider_than_a_quarter(parts),
        _halve,
        batch=2,
        deadline=float("inf"),
        max_nodes=3,
        exact_budget=True,
    )
    assert (first.nodes, first.stopped) == (3, "nodes") and first.left
    rest = branch_and_bound(
        None,
        None,
        _wider_than_a_quarter(parts),
        _halve,
        batch=2,
        deadline=float("inf"),
        queue=first.left,
    )
    assert parts == whole and first.nodes + rest.nodes == once.nodes == 7
    assert (rest.stopped, rest.left, rest.depth) == (None, [], once.depth)
    assert first.depth == 1  # the deepest level it took

    late = branch_and_bound(
        root, state, _wider_than_a_quarter([]), _halve, batch=2, deadline=0.0, level=5
    )
    assert (late.nodes, late.stopped, late.depth) == (0, "time", 5)
    ((nodes, kept, level),) = late.left
    assert torch.equal(nodes, root) and torch.equal(kept, state) and level == 5


def test_an_unbounded_batch_does_not_count_against_the_node_budget():
    calls = []

    def decide(nodes, state, level):
        calls.append(level)
        return Step(state, torch.ones(len(nodes), dtype=torch.bool), bounded=level > 0)

    root, state = torch.tensor([[0.0, 1.0]]), torch.ones(1, 1, dtype=torch.bool)
    done = branch_and_bound(
        root, state, decide, _halve, batch=2, deadline=float("inf"), max_nodes=2
    )
    assert calls == [0, 1] and done.nodes == 2 and done.stopped == "nodes"


def test_the_default_batch_keeps_the_largest_bound_tensor_within_memory():
    """Nodes per batch: ``memory`` over the centre and radius stacks of the largest value
    (rows: the set's, plus a zonotope's symbols; or ``widest``), between 1 and 64."""
    net = nn.Sequential(nn.Linear(6, 10), nn.ReLU(), nn.Linear(10, 4)).double()
    hull = ConvexHull(torch.randn(3, 6, dtype=torch.float64))  # 3 rows: 1 + 2 parameters
    graph = trace(net, hull.example_input())
    one = 2 * 3 * 10  # elements of one node's two stacks of the largest value
    assert default_batch(graph, hull, False, memory=5 * one) == 5
    assert default_batch(graph, hull, False, memory=5 * one + one - 1) == 5
    assert default_batch(graph, hull, False, memory=one - 1) == 1
    assert default_batch(graph, hull, False, memory=1000 * one) == 64
    assert default_batch(graph, hull, False, memory=5 * one, widest=20) == 2
    # A zonotope's stacks carry one symbol per ReLU neuron too (10 here).
    assert default_batch(graph, hull, True, memory=2 * (3 + 10) * 10 * 4) == 4


def test_the_absolute_tolerance_scales_with_the_outputs_at_the_first_point():
    net = nn.Sequential(nn.Linear(2, 2, bias=False)).double()
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0, 0.0], [0.0, -3.0]]))
    hull = ConvexHull(torch.tensor([[1.0, 2.0], [0.0, 0.0]], dtype=torch.float64))
    graph = trace(net, hull.example_input())
    assert absolute_tol(graph, hull, 1e-6) == pytest.approx(1e-6 * (1 + 6.0))


@pytest.mark.parametrize(
    "args, kwargs, message",
    [
        ((0, None, None), {}, "^timeout"),
        ((float("nan"), None, None), {}, "^timeout"),
        ((1.0, 0, None), {}, "^max_nodes"),
        ((1.0, 1, None), {"least_nodes": 2}, "^max_nodes"),
        ((1.0, 2.5, None), {}, "^max_nodes"),
        ((1.0, None, 0), {}, "^batch"),
    ],
)
def test_a_bad_budget_is_refused_by_name(args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        check_budget(*args, **kwargs)
    check_budget(1.0, None, None)
    check_budget(0.5, 2, 8, least_nodes=2)
