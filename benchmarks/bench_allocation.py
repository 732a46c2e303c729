"""Allocation time per image (exact MILP optimum), CNN (64) and ResNet-18 (256) heatmaps.

Ours: :func:`kpstudy.pose.allocation.allocate_tolerances` per image (cached parameterised
one-hot model, Lagrangian bound tightening, cvxpy + HiGHS at zero gap), and per allocation
of the same grid batched by :func:`kpstudy.pose.allocation.allocate_many` in ``--workers``
processes. Baseline: docs/design.md §4.3's textbook model built per call, ``δv_j = Σ_i z_ji``
with binary increments weighted by ``f(i) − f(i−1)``, same solver, gap and feasibility
tolerances (with HiGHS's default 1e-7 the textbook model returns points that violate
``κ|M|δv ≤ ε`` by 4e-7 after rounding). Both must reach the same objective.
"""

from __future__ import annotations

import argparse
import statistics
import time

import cvxpy as cp
import numpy as np

from benchmarks.common import HEATMAP_SCALE, emit, scene
from kpstudy.pose.allocation import _HIGHS_OPTIONS, allocate_many, allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T
from kpstudy.pose.pnp import solve_pnp
from kpstudy.pose.sensitivity import pose_sensitivity


def baseline(M, eps_r, eps_t, kappa=1.0, w1=1.0, w2=5.0, max_dv=64) -> float:
    """Objective of the incremental-binary MILP, built from scratch."""
    A = kappa * np.abs(M) / np.r_[eps_r, eps_t][:, None]
    n = M.shape[1]
    z = cp.Variable((n, max_dv), boolean=True)
    delta = cp.Variable()
    dv = cp.sum(z, axis=1)
    gain = np.diff(np.log(2.0 * np.arange(max_dv + 1) + 1.0))
    problem = cp.Problem(
        cp.Maximize(w1 * cp.sum(z @ gain) + w2 * delta),
        [A @ dv <= 1 - 1e-9, dv >= delta, delta >= 0],
    )
    problem.solve(solver=cp.HIGHS, **_HIGHS_OPTIONS)  # the same tolerances as ours
    x = np.rint(dv.value)
    if np.any(A @ x > 1.0):
        raise RuntimeError("baseline allocation infeasible after rounding")
    return float(problem.value)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--baseline-images", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2, help="processes for the batch figure")
    args = ap.parse_args(argv)
    P, K, _, _, V = scene(args.images, noise_px=0.0)
    res = {"images": args.images, "baseline_images": args.baseline_images}
    for heatmap in (64, 256):
        scale = tuple(s * heatmap / 64 for s in HEATMAP_SCALE)
        Ms = [pose_sensitivity(P, v, K, *solve_pnp(P, v, K), scale=scale) for v in V]
        problems, objectives = [], []
        for alpha in (0.5, 1.0, 2.0):
            eps = (alpha * EPS_R, alpha * EPS_T)
            problems += [(M, *eps) for M in Ms]
            ours, base, gap = [], [], 0.0
            for i, M in enumerate(Ms):
                start = time.perf_counter()
                a = allocate_tolerances(M, *eps, max_dv=heatmap)
                ours.append(time.perf_counter() - start)
                objectives.append(a.objective)
                if i < args.baseline_images:
                    start = time.perf_counter()
                    j = baseline(M, *eps, max_dv=heatmap)
                    base.append(time.perf_counter() - start)
                    gap = max(gap, abs(j - a.objective))
            key = f"heatmap{heatmap}_alpha{alpha}"
            res[f"{key}_ours_median_s"] = statistics.median(ours)
            res[f"{key}_ours_max_s"] = max(ours)
            res[f"{key}_baseline_median_s"] = statistics.median(base)
            res[f"{key}_max_objective_difference"] = gap
        # The same allocations (all three α) as one batch in worker processes, start-up
        # included: the time per allocation of a study's grid.
        start = time.perf_counter()
        batch = allocate_many(problems, workers=args.workers, max_dv=heatmap)
        seconds = (time.perf_counter() - start) / len(problems)
        res[f"heatmap{heatmap}_batch_s_per_allocation_{args.workers}_workers"] = seconds
        if any(b.objective != a for b, a in zip(batch, objectives)):
            raise RuntimeError("allocate_many disagrees with allocate_tolerances")
    return emit("allocation_per_image", res)


if __name__ == "__main__":
    main()
