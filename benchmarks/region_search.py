"""The pose-bound method's region search, model beside model: seconds per node.

For object (or block) hulls of the study's perturbation sets (``--data``; per ``--m``
and overlap, the first seed image from ``--seed-index`` with ``m`` such images, as in
``bound_profile``) or the brightness or contrast hull of that seed image (``--level``;
``--nodes 1`` times a root proof), the search :func:`kpstudy.certify.pose_bound` makes
at stride 1 (the argmax head's own pixels: :func:`kpstudy.verify.reachable_argmax` on
the backbone) with ``--method`` bounds, ``--start-depth`` splits before the first bounds
and a budget of ``--nodes``. Prints one JSON line: per checkpoint × hull, the seconds,
nodes, seconds per node, what stopped the search, whether the regions are complete (one
witnessed pixel per possible one) and the mean possible pixels per keypoint. With
``--baseline``, each search runs again with ``tail_first=False`` (every node's symbols
through the whole network) and its seconds and nodes stand beside the first run's.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.bound_profile import _checkpoint
from benchmarks.common import emit, study_hulls
from kpstudy.certify.pose_bound_regions import search_regions
from kpstudy.models.data import load_keypoint_set
from kpstudy.models.preprocess import scale_factors, to_input_pixels, to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.verify import ConvexHull


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--checkpoint", type=_checkpoint, nargs="+", required=True)
    ap.add_argument("--data", type=Path, required=True, help="a dataset with perturbation sets")
    ap.add_argument("--kind", default="objects", help="objects, blocks, brightness or contrast")
    ap.add_argument("--level", type=float, help="brightness or contrast level (the first)")
    ap.add_argument("--m", type=int, nargs="+", default=[2, 3, 4])
    ap.add_argument("--overlapping", choices=("no", "yes", "both"), default="no")
    ap.add_argument("--seed-index", type=int, default=0)
    ap.add_argument("--method", default="zonotope", help="forward, zonotope or ibp")
    ap.add_argument("--nodes", type=int, default=4, help="node budget per hull")
    ap.add_argument("--start-depth", type=int, default=2)
    ap.add_argument("--batch", type=int, help="nodes bounded together (default: the search's)")
    ap.add_argument("--timeout", type=float, default=600.0, help="a cap, seconds per hull")
    ap.add_argument("--baseline", action="store_true", help="rerun each search without tail_first")
    args = ap.parse_args(argv)
    level, hulls = study_hulls(
        args.data, args.kind, args.m, args.overlapping, args.seed_index, args.level
    )
    out = {"kind": args.kind, "level": level, "method": args.method, "nodes": args.nodes}
    out["runs"] = []
    for name, path in args.checkpoint:
        net, _ = load_checkpoint(path)
        net.eval()
        hm = net.heatmap_size
        test = load_keypoint_set(args.data, "test", net.input_size)
        for hull_args in hulls:
            index = list(test.image_ids).index(hull_args["image_id"])
            uv = np.asarray(test.image_keypoints[index], dtype=np.float64)
            factors = scale_factors(tuple(test.image_size), hm)
            centers = np.clip(np.rint(to_input_pixels(uv, factors)), 0, hm - 1).astype(np.int64)
            hull = ConvexHull(to_model_input(hull_args["V"], size=net.input_size))
            search = dict(
                method=args.method,
                timeout=args.timeout,
                max_nodes=args.nodes,
                start_depth=args.start_depth,
                batch=args.batch,
            )
            start = time.perf_counter()
            regions, _ = search_regions(net, hull, centers, 1, search)
            seconds = time.perf_counter() - start
            baseline = {}
            if args.baseline:
                start = time.perf_counter()
                whole, _ = search_regions(net, hull, centers, 1, dict(search, tail_first=False))
                baseline = {
                    "baseline_seconds": time.perf_counter() - start,
                    "baseline_nodes": whole.nodes,
                    "same_sets": all(
                        a.tolist() == b.tolist() for a, b in zip(regions.possible, whole.possible)
                    ),
                }
            out["runs"].append(
                {
                    "checkpoint": name,
                    **{k: hull_args[k] for k in ("image_id", "m", "overlapping")},
                    "seconds": seconds,
                    "nodes": regions.nodes,
                    "seconds_per_node": seconds / max(regions.nodes, 1),
                    "stopped": regions.stats["stopped"],
                    "complete": regions.complete,
                    "mean_pixels": float(np.mean([len(p) for p in regions.possible])),
                    **baseline,
                }
            )
    return emit("region_search", out)


if __name__ == "__main__":
    main()
