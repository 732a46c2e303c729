"""Allocation time per image (cvxpy + HiGHS MILP, exact optimum), CNN and ResNet-18 heatmaps.

Baseline: the same MILP built and solved from scratch each call (no cached cvxpy problem).
"""

from __future__ import annotations

import argparse
import statistics
import time

from benchmarks.common import HEATMAP_SCALE, emit, scene
from kpstudy.allocation import allocate_tolerances
from kpstudy.montecarlo import EPS_R, EPS_T
from kpstudy.pnp import solve_pnp
from kpstudy.sensitivity import pose_sensitivity


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--images", type=int, default=100)
    args = ap.parse_args(argv)
    P, K, _, _, V = scene(args.images, noise_px=0.0)
    res = {"images": args.images}
    for heatmap in (64, 256):
        scale = tuple(s * heatmap / 64 for s in HEATMAP_SCALE)
        Ms = [pose_sensitivity(P, v, K, *solve_pnp(P, v, K), scale=scale) for v in V]
        for alpha in (0.5, 1.0, 2.0):
            times = []
            for M in Ms:
                start = time.perf_counter()
                allocate_tolerances(M, alpha * EPS_R, alpha * EPS_T, max_dv=heatmap)
                times.append(time.perf_counter() - start)
            res[f"heatmap{heatmap}_alpha{alpha}_median_s"] = statistics.median(times)
            res[f"heatmap{heatmap}_alpha{alpha}_max_s"] = max(times)
    return emit("allocation_per_image", res)


if __name__ == "__main__":
    main()
