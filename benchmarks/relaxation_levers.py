"""Relaxation levers on one search node, side by side: what each leaves possible, at what cost.

For object (or block) hulls of the study's perturbation sets (``--data``; per ``--m``, the
first seed image from ``--seed-index`` with ``m`` such images, as in ``bound_profile``)
each hull is split ``--depth`` times, as the region search splits it, and node
``--node`` of that level (``-1``: the one the zonotope leaves the most possible pixels
in) is bounded as a hull of its own (one node of
:func:`kpstudy.verify.reachable_argmax`, every keypoint's heatmap at stride 1, the
zonotope) by each lever:

``zonotope``
    the search's bounds (DeepZ), as the study runs them;
``split``
    the node's ``2^n`` descendants after ``n`` more bisections (``n`` the hull's
    dimension: each direction halved), the union of their possible sets;
``slopes``
    DeepZ with each unstable ReLU's slope ``λ ∈ [0, 1]`` optimised by gradient
    (α-CROWN's idea on the zonotope: ``y = λx + β + β·ε`` with
    ``2β = max(−λl, (1 − λ)u)``, sound for every ``λ``), ``--steps`` Adam steps on the
    summed gap between each keypoint's pixel upper bounds and its best lower bound;
``crown``
    each ReLU's pre-activation bounds tightened, before it is relaxed, by CROWN
    back-substitution of its unstable neurons to the input through the relaxations made
    so far (DeepPoly's intermediate bounds on top of the zonotope's);
``oracle``
    not a method (sampling decides it): every ReLU the bounds leave unstable but
    ``--samples`` images of the node see on one side only is fixed to that side. It is
    what perfectly tight intermediate bounds, or neuron branching that pruned every
    infeasible phase for free, could gain at most.

Prints one JSON line: per checkpoint × hull, the node's level and index and, per lever,
the possible pixels summed over the keypoints (``possible``; 23 is one per keypoint),
the most in one keypoint, the seconds (``slopes``: with its optimisation) and, for
``crown`` and ``oracle``, the unstable ReLUs per layer before and after.
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from pathlib import Path

import torch

from benchmarks.bound_profile import _checkpoint
from benchmarks.common import emit, study_hulls
from kpstudy.models.preprocess import to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.verify import ConvexHull, bounds, operators, reachable_argmax
from kpstudy.verify.graph import trace
from kpstudy.verify.profile import sampled_ranges

LEVERS = ("zonotope", "split", "slopes", "crown", "oracle")
#: Deepest level whose nodes ``--node -1`` bounds all, to find the loosest.
MAX_SCAN_DEPTH = 10
#: One node of the region search (the levers' unit; node budgets, no time cap).
SEARCH = dict(method="zonotope", samples=16, timeout=1e9, batch=1, max_nodes=1)


@contextmanager
def relu_rules(rules: operators.ReLURules):
    """Bound every ReLU with ``rules`` inside the block."""
    old = operators.RULES["relu"]
    operators.RULES["relu"] = rules
    try:
        yield rules
    finally:
        operators.RULES["relu"] = old


def unstable(l, u) -> int:
    return int(((l < 0) & (u > 0)).sum())


class Recorded(operators.ReLURules):
    """DeepZ, keeping each ReLU's slopes ``s`` (``seen[i]``)."""

    def __init__(self):
        self.seen = {}

    def _deepz(self, p, i, l, u):
        s, mu = operators.ReLURules._deepz(p, i, l, u)
        self.seen[i] = s.detach().clone()
        return s, mu


class Slopes(operators.ReLURules):
    """DeepZ with the slopes ``λ`` of ``slopes[i]`` (clamped to [0, 1]) where unstable."""

    def __init__(self, slopes: dict):
        self.slopes = slopes

    def _deepz(self, p, i, l, u):
        s, mu = operators.ReLURules._deepz(p, i, l, u)
        if i not in self.slopes:
            return s, mu
        varying = (l < 0) & (u > 0)
        lam = torch.where(varying, self.slopes[i].clamp(0, 1), s)
        beta = torch.where(varying, torch.maximum(-lam * l, (1 - lam) * u) / 2, 0.0)
        return lam, beta


class Tightened(operators.ReLURules):
    """DeepZ on pre-activation bounds tightened by CROWN from ``region`` (one region)."""

    def __init__(self, region, rows: int = 512):
        self.region, self.rows, self.counts = region, rows, {}

    def _deepz(self, p, i, l, u):
        j = p.graph.nodes[i].inputs[0]
        lf, uf = l.view(-1), u.view(-1)  # l, u are fresh tensors of this rule's caller
        before = unstable(l, u)
        for part in ((lf < 0) & (uf > 0)).nonzero().flatten().split(self.rows):
            none = torch.full_like(part, -1)
            low = bounds.backward(p.graph, self.region, p.saved, part, none, start=j)[0]
            high = -bounds.backward(p.graph, self.region, p.saved, none, part, start=j)[0]
            lf[part] = torch.maximum(lf[part], low)
            uf[part] = torch.minimum(uf[part], high)
        self.counts[i] = (before, unstable(l, u))
        return operators.ReLURules._deepz(p, i, l, u)


class Oracle(operators.ReLURules):
    """DeepZ with every neuron that ``low, high`` (sampled pre-activation ranges per
    graph node) see on one side of 0 fixed to that side. Not sound: a yardstick."""

    def __init__(self, low: dict, high: dict):
        self.low, self.high, self.counts = low, high, {}

    def _deepz(self, p, i, l, u):
        j = p.graph.nodes[i].inputs[0]
        before = unstable(l, u)
        l = torch.where((self.low[j] >= 0) & (l < 0), 0.0, l)
        u = torch.where((self.high[j] <= 0) & (u > 0), 0.0, u)
        self.counts[i] = (before, unstable(l, u))
        return operators.ReLURules._deepz(p, i, l, u)


def optimise_slopes(graph, region, steps: int, lr: float) -> dict:
    """Adam on DeepZ's slopes (from DeepZ's own) for the summed gap between every pixel's
    upper bound and its keypoint's best lower bound; the slopes after ``steps``."""
    with relu_rules(Recorded()) as seen, torch.no_grad():
        bounds.propagate(graph, region, zonotope=True, dense=False)
    slopes = {i: s.requires_grad_(True) for i, s in seen.seen.items()}
    opt = torch.optim.Adam(list(slopes.values()), lr=lr)
    G = graph.nodes[-1].shape[0]
    with relu_rules(Slopes(slopes)), torch.enable_grad():
        for _ in range(steps):
            out, _ = bounds.propagate(graph, region, zonotope=True, dense=False)
            low, high = (b.reshape(G, -1) for b in out.bounds())
            loss = (high - low.amax(-1, keepdim=True)).clamp_min(0).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            with torch.no_grad():
                for s in slopes.values():
                    s.clamp_(0, 1)
    return {i: s.detach() for i, s in slopes.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--checkpoint", type=_checkpoint, nargs="+", required=True)
    ap.add_argument("--data", type=Path, required=True, help="a dataset with perturbation sets")
    ap.add_argument("--kind", default="objects", help="objects or blocks")
    ap.add_argument("--m", type=int, nargs="+", default=[3])
    ap.add_argument("--overlapping", choices=("no", "yes", "both"), default="no")
    ap.add_argument("--seed-index", type=int, default=0)
    ap.add_argument("--depth", type=int, nargs="+", default=[4], help="splits of the hull")
    ap.add_argument(
        "--node", type=int, default=-1, help="which node of that level (-1: the loosest)"
    )
    ap.add_argument("--levers", nargs="+", choices=LEVERS, default=list(LEVERS))
    ap.add_argument("--steps", type=int, default=20, help="slopes: Adam steps")
    ap.add_argument("--lr", type=float, default=0.01, help="slopes: Adam's step size")
    ap.add_argument("--samples", type=int, default=384, help="oracle: images of the node")
    args = ap.parse_args(argv)
    if min(args.depth) < 0 or args.node < -1:
        ap.error(
            f"--depth, --node: expected integers >= 0 (--node -1), got {args.depth}, {args.node}"
        )
    if args.node >= 2 ** min(args.depth):
        ap.error(
            f"--node: expected < {2 ** min(args.depth)} at depth {min(args.depth)}, got {args.node}"
        )
    if args.node < 0 and max(args.depth) > MAX_SCAN_DEPTH:
        ap.error(f"--node -1: expected every --depth <= {MAX_SCAN_DEPTH}, got {args.depth}")
    _, hulls = study_hulls(args.data, args.kind, args.m, args.overlapping, args.seed_index)
    out = {"kind": args.kind, "steps": args.steps, "lr": args.lr, "runs": []}
    for name, path in args.checkpoint:
        net, _ = load_checkpoint(path)
        net.eval().requires_grad_(False)
        for hull_args in hulls:
            hull = ConvexHull(to_model_input(hull_args["V"], size=net.input_size))
            for depth in args.depth:
                indices = [args.node] if args.node >= 0 else range(2**depth)
                cells = {k: node_at(hull, depth, k) for k in indices}
                index = args.node if args.node >= 0 else loosest(net, cells)
                run = {
                    "checkpoint": name,
                    **{k: hull_args[k] for k in ("image_id", "m", "overlapping")},
                    "depth": depth,
                    "node": index,
                }
                node = cells[index]
                run.update(levers(net, node, args))
                out["runs"].append(run)
    return emit("relaxation_levers", out)


def possible_pixels(net, node: ConvexHull, **search) -> dict:
    """One :func:`reachable_argmax` on ``node`` with the zonotope, every keypoint's
    heatmap: its possible pixels (summed, most in one keypoint) and seconds."""
    G, H, W = trace(net, node.example_input()).nodes[-1].shape
    start = time.perf_counter()
    regions = reachable_argmax(net, node, [H * W] * G, **{**SEARCH, **search})
    return {
        "possible": int(sum(len(p) for p in regions.possible)),
        "most": int(max(len(p) for p in regions.possible)),
        "seconds": time.perf_counter() - start,
    }


def node_at(hull: ConvexHull, depth: int, index: int) -> ConvexHull:
    """Node ``index`` of ``hull`` split ``depth`` times (the order of
    :meth:`~kpstudy.verify.sets.ConvexHull.split`: a level's left children, then its right
    ones), as a hull of its own: bit ``L`` of ``index`` says which child of level ``L``."""
    nodes = hull.root()
    for level in range(depth):
        side = (index >> level) & 1
        nodes = hull.split(nodes)[side : side + 1]
    return ConvexHull(hull.image(nodes[0], dtype=hull.dtype))


def loosest(net, nodes: dict) -> int:
    """The key of the node the zonotope leaves the most possible pixels in."""
    return max(nodes, key=lambda k: possible_pixels(net, nodes[k])["possible"])


def levers(net, node: ConvexHull, args) -> dict:
    """Each lever of ``args.levers`` on ``node``: possible pixels, seconds, counts."""
    graph = trace(net, node.example_input())
    region = node.region(node.root(), graph.dtype)

    result = {}
    for lever in args.levers:
        if lever == "zonotope":
            result[lever] = possible_pixels(net, node)
        elif lever == "split":
            result[lever] = possible_pixels(net, node, max_nodes=2**node.n, start_depth=node.n)
        elif lever == "slopes":
            start = time.perf_counter()
            slopes = optimise_slopes(graph, region, args.steps, args.lr)
            spent = time.perf_counter() - start
            with relu_rules(Slopes(slopes)):
                result[lever] = possible_pixels(net, node)
            result[lever]["seconds"] += spent
        elif lever == "crown":
            with relu_rules(Tightened(region)) as rules:
                result[lever] = possible_pixels(net, node)
            result[lever]["unstable"] = list(rules.counts.values())
        else:
            images = node.image(node.sample(args.samples, 0)).to(graph.dtype)
            corners = node.image(node.sample(max(1, args.samples // 4), 1, "vertices"))
            low, high = sampled_ranges(graph, torch.cat([images, corners.to(graph.dtype)]), 16)
            with relu_rules(Oracle(low, high)) as rules:
                result[lever] = possible_pixels(net, node)
            result[lever]["unstable"] = list(rules.counts.values())
    return result


if __name__ == "__main__":
    main()
