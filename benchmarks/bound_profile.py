"""Bound tightness layer by layer: zonotope vs forward (vs IBP), model beside model.

For hulls of the study's perturbation sets (``--data``, ``python -m data_gen perturb``)
around a seed image (object and block hulls: the first from ``--seed-index`` with ``m``
such images), :func:`kpstudy.verify.bound_profile` bounds every node of each
backbone (``--checkpoint NAME=PATH …``, e.g. the natural CNN and the verification-friendly
one) over the exact hull with each method and compares the bound width with the range
reached by sampled hull images (ratio 1 = exact), and the ReLUs each method leaves
unstable with those whose sign the samples see change (``--scales``: also sub-hulls shrunk
towards the seed image, as a branch and bound's nodes are; ``--depths``: also the union of
the bounds of the hull's nodes after that many splits, what a search from that start
depth begins with). Object and block hulls are profiled for every ``--m`` and overlap;
every checkpoint sees the same hulls. Prints one JSON line: per run (checkpoint × hull ×
scale × depth) and method, the seconds, ``heatmap_ratio`` (the output's
``ratio_median``), ``heatmap_ratio_total`` and, per ReLU and for the output,
``ratio_median``, ``ratio_total``, ``unstable_bound`` and ``unstable_sampled``.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import torch

from benchmarks.common import emit, study_hulls
from kpstudy.models.preprocess import to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.verify import ConvexHull, bound_profile

COLUMNS = ("name", "ratio_median", "ratio_total", "unstable_bound", "unstable_sampled")


def _checkpoint(text: str) -> tuple[str, Path]:
    name, _, path = text.rpartition("=")
    return (name or Path(path).stem), Path(path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument(
        "--checkpoint",
        type=_checkpoint,
        nargs="+",
        required=True,
        help="NAME=PATH or PATH (python -m kpstudy train), one or more",
    )
    ap.add_argument("--data", type=Path, required=True, help="a dataset with perturbation sets")
    ap.add_argument("--kind", default="brightness", help="objects, blocks, brightness, contrast")
    ap.add_argument("--level", type=float, help="brightness or contrast level (default: the first)")
    ap.add_argument("--m", type=int, nargs="+", default=[2], help="objects and blocks: sizes")
    ap.add_argument(
        "--overlapping", choices=("no", "yes", "both"), default="no", help="objects and blocks"
    )
    ap.add_argument("--seed-index", type=int, default=0, help="which seed image of the set")
    ap.add_argument("--methods", nargs="+", default=["ibp", "forward", "zonotope"])
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument(
        "--scales",
        type=float,
        nargs="+",
        default=[1.0],
        help="also profile sub-hulls shrunk towards the seed image by these factors in (0, 1]",
    )
    ap.add_argument(
        "--depths",
        type=int,
        nargs="+",
        default=[0],
        help="also bound the union of the hull's 2^D nodes after D splits (0: the root)",
    )
    args = ap.parse_args(argv)
    if not all(d >= 0 for d in args.depths):
        ap.error(f"--depths: expected integers >= 0, got {args.depths}")
    if not all(0 < v <= 1 for v in args.scales):
        ap.error(f"--scales: expected factors in (0, 1], got {args.scales}")
    level, hulls = study_hulls(
        args.data, args.kind, args.m, args.overlapping, args.seed_index, args.level
    )
    out = {"kind": args.kind, "level": level, "runs": []}
    for name, path in args.checkpoint:
        net, _ = load_checkpoint(path)
        net.eval()
        for hull_args in hulls:
            V = hull_args["V"]
            full = to_model_input(V, size=net.input_size)
            for scale, depth in itertools.product(args.scales, args.depths):
                hull = ConvexHull(torch.cat([full[:1], full[:1] + scale * (full[1:] - full[:1])]))
                run = {
                    "checkpoint": name,
                    **{k: hull_args[k] for k in ("image_id", "m", "overlapping")},
                    "scale": scale,
                    "depth": depth,
                }
                for method in args.methods:
                    start = time.perf_counter()
                    profile = bound_profile(
                        net, hull, method=method, samples=args.samples, depth=depth
                    )
                    keep = [r for r in profile if r["op"] == "ReLU"] + profile[-1:]
                    run[method] = {
                        "seconds": time.perf_counter() - start,
                        "contained": all(r["contained"] for r in profile),
                        "heatmap_ratio": profile[-1]["ratio_median"],
                        "heatmap_ratio_total": profile[-1]["ratio_total"],
                        "layers": [{k: r.get(k) for k in COLUMNS} for r in keep],
                    }
                out["runs"].append(run)
    return emit("bound_profile", out)


if __name__ == "__main__":
    main()
