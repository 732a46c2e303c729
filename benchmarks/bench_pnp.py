"""Batched PnP (torch LM) vs a cv2.solvePnP loop on the same 23-point problems.

Both start from the same initial pose (the nominal pose, as in the Monte Carlo study);
the baseline is OpenCV's own LM (SOLVEPNP_ITERATIVE with an extrinsic guess), and
also the global SQPnP + LM refinement that :func:`kpstudy.pose.pnp.solve_pnp` uses.
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from benchmarks.common import emit, scene, timed
from kpstudy.pose.pnp import solve_pnp, solve_pnp_batch


def cv2_loop_guess(P, V, K, R, t):
    out = []
    for Vi, Ri, ti in zip(V, R, t):
        rvec = cv2.Rodrigues(Ri)[0]
        _, rvec, tvec = cv2.solvePnP(
            P, Vi, K, None, rvec, ti.copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
        )
        out.append(tvec)
    return out


def sqpnp_loop(P, V, K):
    return [solve_pnp(P, Vi, K) for Vi in V]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--problems", type=int, default=100_000)
    ap.add_argument("--baseline-problems", type=int, default=10_000)
    ap.add_argument("--compile", action="store_true", help="also time the torch.compile path")
    args = ap.parse_args(argv)
    P, K, R, t, V = scene(args.problems)
    nb = args.baseline_problems
    s_ours, (R_b, t_b) = timed(solve_pnp_batch, P, V, K, (R, t))
    s_cv, _ = timed(cv2_loop_guess, P, V[:nb], K, R[:nb], t[:nb])
    s_sq, _ = timed(sqpnp_loop, P, V[:nb], K)
    agree = max(np.abs(solve_pnp(P, V[i], K)[1] - t_b[i]).max() for i in range(200))
    res = {
        "problems": args.problems,
        "ours_solves_per_s": args.problems / s_ours,
        "cv2_iterative_guess_solves_per_s": nb / s_cv,
        "cv2_sqpnp_lm_solves_per_s": nb / s_sq,
        "speedup_vs_cv2_iterative": (args.problems / s_ours) / (nb / s_cv),
        "speedup_vs_sqpnp_lm": (args.problems / s_ours) / (nb / s_sq),
        "max_abs_t_difference_m_200_problems": float(agree),
    }
    if args.compile:
        # Compile once (static chunk, then the dynamic shapes of the straggler sets).
        s_first, _ = timed(
            solve_pnp_batch, P, V[:20_000], K, (R[:20_000], t[:20_000]), compile=True
        )
        s_c, _ = timed(solve_pnp_batch, P, V, K, (R, t), compile=True)
        res["ours_compiled_solves_per_s"] = args.problems / s_c
        res["speedup_compiled_vs_cv2_iterative"] = (args.problems / s_c) / (nb / s_cv)
        res["compile_seconds_first_call"] = s_first
    return emit("pnp_batch_vs_cv2_loop", res)


if __name__ == "__main__":
    main()
