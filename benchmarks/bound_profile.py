"""Bound tightness layer by layer on the trained CNN: zonotope vs forward (vs IBP).

For one hull of the study's perturbation sets (``--data``, ``python -m data_gen perturb``)
around a seed image, :func:`kpstudy.verify.bound_profile` bounds every node of the
backbone over the exact hull with each method and compares the bound width with the range
reached by sampled hull images (ratio 1 = exact), and the ReLUs each method leaves
unstable with those whose sign the samples see change. Prints one JSON line: per method,
the seconds and, per ReLU and for the output, ``ratio_median``, ``unstable_bound`` and
``unstable_sampled``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import emit
from kpstudy.preprocess import normalise, resize_to_input
from kpstudy.train import load_checkpoint
from kpstudy.verify import ConvexHull, bound_profile

COLUMNS = ("name", "ratio_median", "unstable_bound", "unstable_sampled")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--checkpoint", type=Path, required=True, help="python -m kpstudy train")
    ap.add_argument("--data", type=Path, required=True, help="a dataset with perturbation sets")
    ap.add_argument("--kind", default="brightness", help="objects, blocks, brightness, contrast")
    ap.add_argument("--level", type=float, help="brightness or contrast level (default: the first)")
    ap.add_argument("--m", type=int, default=2, help="objects and blocks: perturbed images")
    ap.add_argument("--seed-index", type=int, default=0, help="which seed image of the set")
    ap.add_argument("--methods", nargs="+", default=["ibp", "forward", "zonotope"])
    ap.add_argument("--samples", type=int, default=500)
    args = ap.parse_args(argv)
    from data_gen.perturb import DEFAULT_LEVELS, hull_vertices, load_perturbations

    rows = load_perturbations(args.data, args.kind)["images"]
    image_id = sorted({r["image_id"] for r in rows})[args.seed_index]
    if args.kind in DEFAULT_LEVELS:
        level = args.level or min(r["level"] for r in rows if r["image_id"] == image_id)
        V = hull_vertices(args.data, image_id, args.kind, level=level)
    else:
        level = None
        V = hull_vertices(args.data, image_id, args.kind, args.m, False)
    net, _ = load_checkpoint(args.checkpoint)
    net.eval()
    x = normalise(np.stack([resize_to_input(v, net.input_size) for v in V]))
    hull = ConvexHull(torch.from_numpy(x).permute(0, 3, 1, 2).contiguous())
    out = {"kind": args.kind, "image_id": image_id, "level": level, "n": hull.n}
    for method in args.methods:
        start = time.perf_counter()
        profile = bound_profile(net, hull, method=method, samples=args.samples)
        keep = [r for r in profile if r["op"] == "ReLU"] + profile[-1:]
        out[method] = {
            "seconds": time.perf_counter() - start,
            "contained": all(r["contained"] for r in profile),
            "layers": [{k: r.get(k) for k in COLUMNS} for r in keep],
        }
    return emit("bound_profile", out)


if __name__ == "__main__":
    main()
