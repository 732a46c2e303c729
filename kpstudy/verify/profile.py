"""Where a bound method loses tightness: a per-node profile against sampled points.

:func:`bound_profile` bounds every node of a traced network over an input set (the root
region, or the union over a branch and bound's start depth; ``'ibp'``, ``'forward'`` or
``'zonotope'``) and compares each node's interval width with the range that sampled
points of the set actually reach. It counts the ReLUs the bounds leave unstable against
those whose input the samples see change sign, and checks that every sampled value lies
within the bounds (the method's soundness at that node). With ``crown_rows``, a random
subset of the varying neurons of each affine node is also bounded by CROWN pulled back
from that node (the earlier ReLUs relaxed from the method's bounds): what
back-substitution would gain there, at what cost. It answers "why is my instance
``unknown``?": on the trained CNN the ``'forward'`` ratio of bound to sampled width grows
~10× per layer (the relaxation, not the search), the ``'zonotope'`` ratio stays near 1 on
small perturbations.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from kpstudy import _checks
from kpstudy.verify import bounds as _bounds
from kpstudy.verify import operators
from kpstudy.verify.graph import Graph, trace

PROFILE_METHODS = ("ibp", "forward", "zonotope")
#: A neuron *varies* over the samples when its sampled range exceeds this fraction of the
#: node's largest magnitude (below it, float32 evaluation noise).
VARYING_RTOL = 1e-4


def bound_profile(
    model,
    input_set,
    *,
    method: str = "forward",
    samples: int = 1000,
    crown_rows: int = 0,
    depth: int = 0,
    seed: int = 0,
    chunk: int = 100,
) -> list[dict]:
    """Per-node tightness of ``method``'s bounds over ``input_set``, against sampling.

    Parameters
    ----------
    model : nn.Module
        Built from the operators of ``kpstudy.verify.graph`` (eval mode).
    input_set : ConvexHull, Parallelotope or Box
    method : {'ibp', 'forward', 'zonotope'}
        How every node is bounded over the whole set (one branch-and-bound root, or each
        node of ``depth``).
    samples : int
        Uniform points of the set, ≥ 1; a quarter as many corners and as many points on
        random edges are added.
    crown_rows : int
        Varying neurons per affine node also bounded by CROWN from that node (0: none).
    depth : int
        Splits of the set before bounding, as a branch and bound's start depth
        (:meth:`~kpstudy.verify.sets.ConvexHull.split`; 0: the root alone): each of the
        ``2^depth`` nodes is bounded on its own and a neuron's bounds are their union, the
        bounds the search starts from. ``crown_rows`` needs ``depth`` 0.
    seed : int
        For the samples and the CROWN subset.
    chunk : int
        Sampled images evaluated at once (memory: ``chunk ×`` the largest activation).

    Returns
    -------
    list of dict
        One per node after the input, in topological order: ``index``, ``name``, ``op``,
        ``shape``; ``varying`` (neurons whose sampled range exceeds
        :data:`VARYING_RTOL` of the node's largest magnitude); ``bound_width_max`` and
        ``sampled_width_max``; ``ratio_median`` (median over varying neurons of bound width
        ÷ sampled width: 1 is exact; NaN if none varies) and ``ratio_total`` (their bound
        widths' sum ÷ their sampled widths' sum: unlike the median, not lowered by the many
        neurons a set barely moves); ``contained`` (every sampled value within the bounds,
        to float32 noise); for ReLU nodes ``unstable_bound`` (its input's bounds straddle
        0) and ``unstable_sampled`` (samples on both sides of 0);
        for affine nodes with ``crown_rows``, ``crown_rows``, ``crown_ratio_median``
        (CROWN ∩ the method's bounds, same subset) and ``crown_seconds``.

    Raises
    ------
    ValueError
        On a bad argument; the message starts with its name.
    """
    _checks.choice(method, "method", PROFILE_METHODS)
    _checks.integer(samples, "samples", minimum=1)
    _checks.integer(crown_rows, "crown_rows", minimum=0)
    _checks.integer(depth, "depth", minimum=0)
    if depth and crown_rows:
        raise ValueError(f"crown_rows: expected 0 with depth {depth}, got {crown_rows}")
    _checks.integer(chunk, "chunk", minimum=1)
    graph = trace(model, input_set.example_input())
    extra = max(1, samples // 4)
    points = [input_set.sample(samples, seed)]
    points += [
        input_set.sample(extra, seed + k, kind) for k, kind in ((1, "vertices"), (2, "edges"))
    ]
    images = input_set.image(torch.cat(points)).to(graph.dtype)
    low_s, high_s = sampled_ranges(graph, images, chunk)

    nodes = input_set.root()
    for _ in range(depth):
        nodes = input_set.split(nodes)
    low_b: dict = {}  # graph node → the union of the set's nodes' bounds (*shape)
    high_b: dict = {}

    def union(i, low, high):
        low_b[i] = low if i not in low_b else torch.minimum(low_b[i], low)
        high_b[i] = high if i not in high_b else torch.maximum(high_b[i], high)

    for node in nodes.split(1):
        region = input_set.region(node, graph.dtype)
        if method == "ibp":
            region = region.to_interval()
        union(0, *(b[0] for b in region.bounds()))

        def keep(i, value):
            low, high = value.bounds()
            union(i, low[0], high[0])

        with torch.no_grad():
            _, saved = _bounds.propagate(graph, region, keep, zonotope=method == "zonotope")
    g = torch.Generator().manual_seed(seed)
    rows = []
    for i, node in enumerate(graph.nodes[1:], start=1):
        lo, hi, s_lo, s_hi = low_b[i], high_b[i], low_s[i], high_s[i]
        scale = float(torch.maximum(s_lo.abs().max(), s_hi.abs().max()))
        noise = 1e-5 * (1.0 + scale)
        width_s = s_hi - s_lo
        varying = width_s > VARYING_RTOL * (1.0 + scale)
        row = {
            "index": i,
            "name": node.name,
            "op": type(node.op).__name__,
            "shape": list(node.shape),
            "varying": int(varying.sum()),
            "bound_width_max": float((hi - lo).max()),
            "sampled_width_max": float(width_s.max()),
            "ratio_median": _median_ratio(hi - lo, width_s, varying),
            "ratio_total": float((hi - lo)[varying].sum() / width_s[varying].sum())
            if varying.any()
            else float("nan"),
            "contained": bool(((s_lo >= lo - noise) & (s_hi <= hi + noise)).all()),
        }
        rule = operators.rules(node.op.kind)
        j = node.inputs[0]
        row.update(rule.profile(low_b[j], high_b[j], low_s[j], high_s[j]))
        if isinstance(rule, operators.AffineRules) and crown_rows and row["varying"]:
            where = torch.nonzero(varying.flatten()).flatten()
            pick = where[torch.randperm(len(where), generator=g)[:crown_rows]]
            none = torch.full_like(pick, -1)
            start = time.perf_counter()
            with torch.no_grad():
                c_lo = _bounds.backward(graph, region, saved, pick, none, start=i)[0]
                c_hi = -_bounds.backward(graph, region, saved, none, pick, start=i)[0]
            c_lo = torch.maximum(c_lo, lo.flatten()[pick])
            c_hi = torch.minimum(c_hi, hi.flatten()[pick])
            sub_lo, sub_hi = s_lo.flatten()[pick], s_hi.flatten()[pick]
            row["crown_rows"] = len(pick)
            row["crown_ratio_median"] = _median_ratio(c_hi - c_lo, sub_hi - sub_lo, None)
            row["crown_seconds"] = time.perf_counter() - start
            row["contained"] &= bool(((sub_lo >= c_lo - noise) & (sub_hi <= c_hi + noise)).all())
        rows.append(row)
    return rows


def sampled_ranges(graph: Graph, images: torch.Tensor, chunk: int = 100):
    """Element-wise min and max of every node's value over ``images`` (lists indexed by
    node), ``chunk`` images at a time."""
    low: list = [None] * len(graph.nodes)
    high: list = [None] * len(graph.nodes)
    with torch.no_grad():
        for part in images.split(chunk):
            values = [part] + [None] * (len(graph.nodes) - 1)
            remaining = [len(c) for c in graph.consumers]
            for i, node in enumerate(graph.nodes):
                v = values[i] = node.op.forward(*(values[j] for j in node.inputs)) if i else part
                lo, hi = v.min(0).values, v.max(0).values
                low[i] = lo if low[i] is None else torch.minimum(low[i], lo)
                high[i] = hi if high[i] is None else torch.maximum(high[i], hi)
                for j in node.inputs:
                    remaining[j] -= 1
                    if remaining[j] == 0:
                        values[j] = None
    return low, high


def _median_ratio(width_bound, width_sampled, mask) -> float:
    if mask is not None:
        width_bound, width_sampled = width_bound[mask], width_sampled[mask]
    if width_bound.numel() == 0:
        return float("nan")
    return float(np.median((width_bound / width_sampled.clamp_min(1e-30)).double().numpy()))
