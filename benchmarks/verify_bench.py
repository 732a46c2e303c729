"""Verification of the paper-sized CNN proxy over convex hulls: ours vs the parallelotope.

The backbone is :class:`kpstudy.models.HeatmapCNN` (64×64×3 → 23 heatmaps 64×64, 6.6e5
parameters): loaded from ``--checkpoint`` (``python -m kpstudy train``) when given, with
the test images of ``--data`` as seeds; otherwise a seeded random
initialisation with batch-norm statistics calibrated on smooth random images (labelled
``"model": "random-init+bn-calibrated"``: its heatmaps have no trained peaks, so the
figures measure the verifier's machinery, not the paper's instances).

Each seed image gets a nominal keypoint per channel (the backbone's heatmap argmax),
proxy pooling of stride 5 (δv = 2), targets the cells that win on the seed, and hulls of
the seed and m = 2, 3, 4 occluded copies (a uniform-colour square pasted at a random
place) or, with ``--perturbation brightness``, the paper's brightness hulls
``[x, clip(x + b), clip(x − b)]`` (b = 1, 2 of 255: keys ``…/1``, ``…/2``), or with
``--perturbation objects|blocks|contrast`` the study's own perturbation sets of ``--data``
(``python -m data_gen perturb``: pasted apron occluders, pixel blocks, contrast levels; keys
``…/2/non-overlapping``, ``…/0.0005``; seeds are the sets' seed images). Every instance
is run for each bound method (default: ``zonotope``, ours, and ``forward``, linear bounds
without error symbols), on the exact :class:`ConvexHull` and on the :class:`Parallelotope`
baseline (ModelVerification.jl's treatment of a hull), with one timeout (checked between
layers too). Peak memory is the process's peak resident set during the instance. Each
instance also reports its worst keypoint's margin bracketed by the root node's lower
bound and the smallest margin the search's attacks found: for an ``unknown`` instance,
how far the bound is from the behaviour seen.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from benchmarks.common import emit, timed
from kpstudy.models import HeatmapCNN, build_proxy
from kpstudy.models.data import load_keypoint_set
from kpstudy.models.pooling import keypoint_pooling
from kpstudy.models.preprocess import to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.verify import ArgmaxSpec, ConvexHull, Parallelotope, verify

STUDY_KINDS = ("objects", "blocks", "contrast")


def seed_image(g: torch.Generator) -> torch.Tensor:
    """A smooth random image ``(3, 64, 64)`` in [0, 1]."""
    return F.interpolate(torch.rand(1, 3, 16, 16, generator=g), size=64, mode="bilinear")[0]


def occluded(x: torch.Tensor, g: torch.Generator, size: int = 10) -> torch.Tensor:
    """``x`` with a ``size``-pixel square of one random colour pasted at a random place."""
    y = x.clone()
    i, j = torch.randint(0, x.shape[-1] - size, (2,), generator=g).tolist()
    y[:, i : i + size, j : j + size] = torch.rand(3, 1, 1, generator=g)
    return y


def brightness(x: torch.Tensor, b: float) -> torch.Tensor:
    """The paper's global perturbation ``clip(x + b)`` (``b`` in 0–255 units)."""
    return (x + b / 255.0).clamp(0.0, 1.0)


def proxy_instance(net, x0: torch.Tensor):
    """The bench's proxy and spec for seed ``x0 (3, 64, 64)``: a nominal keypoint per
    channel at the backbone's heatmap argmax, δv = 2 cells, targets the cells that win on
    the seed (so the property holds at ``x0``)."""
    with torch.no_grad():
        idx = net(x0[None])[0].flatten(1).argmax(1)
    centers = torch.stack([idx % 64, idx // 64], 1).tolist()
    proxy = build_proxy(net, keypoint_pooling(centers, [(2, 2)] * len(centers), (64, 64)))
    spec = ArgmaxSpec([p.n_v * p.n_h for p in proxy.pools], [0] * len(centers))
    with torch.no_grad():
        y = proxy(x0[None])[0]
    wins = [int(y[a:b].argmax()) for a, b in zip(spec.offsets[:-1], spec.offsets[1:])]
    return proxy, ArgmaxSpec(spec.group_sizes, wins)


def instances(
    net, count: int, ms, seed: int, perturbation: str = "occlusion", images=None, square: int = 10
):
    """``count`` seeds × hull sizes: (label, proxy, spec, vertices). Occlusion hulls have
    ``m`` in ``ms`` occluded copies (label m); brightness hulls are ``[x, x + b, x − b]``
    for ``b`` = 1, 2 (label b). Seeds are ``images`` ``(N, 3, 64, 64)`` in [0, 1] when
    given, else smooth random images."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(count):
        x0 = seed_image(g) if images is None else images[i]
        proxy, spec = proxy_instance(net, x0)
        if perturbation == "brightness":
            for b in (1, 2):
                V = torch.stack([x0, brightness(x0, b), brightness(x0, -b)])
                out.append((b, proxy, spec, V))
            continue
        for m in ms:
            out.append(
                (m, proxy, spec, torch.stack([x0] + [occluded(x0, g, square) for _ in range(m)]))
            )
    return out


def study_instances(net, data: Path, kind: str, count: int, ms, seed: int):
    """Hulls of the study's own perturbation sets (``python -m data_gen perturb``) at the
    model input: (label, proxy, spec, vertices) for the first ``count`` seed images.
    Objects and blocks: ``m`` in ``ms`` non-overlapping and overlapping images (label
    ``m/non-overlapping`` …, where the set has that many); contrast: every stored level
    (label the level). (The study's brightness set is ``--perturbation brightness``.)"""
    from data_gen.perturb import DEFAULT_LEVELS, hull_vertices, load_perturbations

    rows = load_perturbations(data, kind)["images"]
    out = []
    for image_id in sorted({r["image_id"] for r in rows})[:count]:
        mine = [r for r in rows if r["image_id"] == image_id]
        if kind in DEFAULT_LEVELS:
            hulls = [
                (f"{level:g}", hull_vertices(data, image_id, kind, level=level))
                for level in sorted({r["level"] for r in mine})
            ]
        else:
            hulls = [
                (
                    f"{m}/{'' if overlap else 'non-'}overlapping",
                    hull_vertices(data, image_id, kind, m, overlap, seed),
                )
                for overlap in (False, True)
                for m in ms
                if m <= sum(r["overlapping"] == overlap for r in mine)
            ]
        for label, V in hulls:
            x = to_model_input(V, size=64)
            out.append((label, *proxy_instance(net, x[0]), x))
    return out


def calibrate_batch_norm(net, seed: int, images: int = 64) -> None:
    """Set batch-norm statistics from smooth random images (a random network's default
    statistics shrink every layer, leaving flat heatmaps with 1e-6 margins)."""
    g = torch.Generator().manual_seed(seed + 1)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None  # cumulative average
    net.train()
    with torch.no_grad():
        net(torch.stack([seed_image(g) for _ in range(images)]))
    net.eval()


def _reset_peak() -> None:
    Path("/proc/self/clear_refs").write_text("5")


def _peak_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--checkpoint", type=Path, help="a CNN checkpoint of python -m kpstudy train")
    ap.add_argument("--data", type=Path, help="dataset whose test images are the seeds")
    ap.add_argument("--seeds", type=int, default=4, help="seed images")
    ap.add_argument("--methods", nargs="+", default=["zonotope", "forward"])
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--square", type=int, default=10, help="occluding square side, pixels")
    ap.add_argument(
        "--perturbation",
        choices=["occlusion", "brightness", *STUDY_KINDS],
        default="occlusion",
        help="random squares or the paper's brightness hulls [x, x+b, x-b] (b = 1, 2) on "
        "the test images of --data, or one of the study's perturbation sets of --data "
        "(python -m data_gen perturb)",
    )
    args = ap.parse_args(argv)
    torch.manual_seed(args.seed)
    if args.checkpoint:
        net, _ = load_checkpoint(args.checkpoint)
    else:
        net = HeatmapCNN(23)
        calibrate_batch_norm(net, args.seed)
    net.eval()
    images = None
    if args.data and args.perturbation not in STUDY_KINDS:
        data = load_keypoint_set(args.data, "test", 64, limit=args.seeds)
        images = to_model_input(data.images)
    if args.perturbation in STUDY_KINDS:
        if not args.data:
            raise SystemExit("--data: needed for the study's perturbation sets")
        cases = study_instances(net, args.data, args.perturbation, args.seeds, (2, 3, 4), args.seed)
    else:
        cases = instances(
            net, args.seeds, (2, 3, 4), args.seed, args.perturbation, images, args.square
        )
    rows = []
    for set_type in (ConvexHull, Parallelotope):
        for method in args.methods:
            for m, proxy, spec, V in cases:
                _reset_peak()
                seconds, r = timed(
                    verify, proxy, set_type(V), spec, method=method, timeout=args.timeout
                )
                rows.append(
                    dict(
                        set=set_type.__name__,
                        method=method,
                        m=m,
                        status=r.status,
                        seconds=seconds,
                        nodes=r.nodes,
                        peak_mib=_peak_mib(),
                        margin_bracket=list(r.margin_bracket()),
                    )
                )
    summary = {}
    for key in sorted({(r["set"], r["method"], r["m"]) for r in rows}):
        sel = [r for r in rows if (r["set"], r["method"], r["m"]) == key]
        t = np.array([r["seconds"] for r in sel])
        summary["/".join(map(str, key))] = {
            "instances": len(sel),
            "median_seconds": float(np.median(t)),
            "mean_seconds": float(t.mean()),
            "median_nodes": float(np.median([r["nodes"] for r in sel])),
            "decided_fraction": float(np.mean([r["status"] != "unknown" for r in sel])),
            "status": dict(Counter(r["status"] for r in sel)),
            "peak_mib": float(max(r["peak_mib"] for r in sel)),
            "worst_margin_root_lower_attack_upper": [r["margin_bracket"] for r in sel],
        }
    return emit(
        "verify_cnn_proxy",
        {
            "model": str(args.checkpoint) if args.checkpoint else "random-init+bn-calibrated",
            "seeds": str(args.data) if args.data else "smooth random images",
            "perturbation": args.perturbation,
            "square": args.square,
            "parameters": sum(p.numel() for p in net.parameters()),
            "spec_rows": cases[0][2].n_rows,
            "timeout_seconds": args.timeout,
            "summary": summary,
        },
    )


if __name__ == "__main__":
    main()
