"""Sensitivity of the PnP pose to its keypoints, by the implicit function theorem.

At the PnP optimum ξ* of ``G(ξ; v) = Σ_k ||π(K (R(ξ) p_k + t)) − v_k||²`` the gradient
``G_ξ`` vanishes for every ``v``, so ``M = dξ/dv = −G_ξξ⁻¹ G_ξv`` (paper §6.1, the extra
δz row of its M̃ vanishes with ``G_ξ``). Both second derivatives are exact, by
``torch.func`` autodiff in float64. ξ = [roll, pitch, yaw (degrees, DESIGN §3),
tx, ty, tz (metres)], v = [u1, v1, u2, v2, …] (pixels).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.func import hessian, jacfwd, jacrev

from kpstudy import _checks
from kpstudy.pose.geometry import euler_from_matrix, matrix_from_euler_torch, project_batch
from kpstudy.pose.pnp import _check_problem

#: Largest keypoint motion (pixels) that one Newton step from (R, t) may cause
#: before (R, t) is refused as not being the PnP optimum of V.
OPTIMUM_TOL_PX = 1e-3


def reprojection_cost(xi: torch.Tensor, v: torch.Tensor, P: torch.Tensor, K: torch.Tensor):
    """``G(ξ; v)``: squared reprojection error, pixels², for ξ (6,) and v (2N,)."""
    R = matrix_from_euler_torch(xi[:3])
    r = project_batch(P, R, xi[3:], K).reshape(-1) - v
    return (r * r).sum()


def pose_sensitivity(P, V, K, R, t, scale=None) -> np.ndarray:
    """dξ/dv at the PnP optimum.

    Parameters
    ----------
    P : array_like, shape (N, 3)
        Object keypoints, metres.
    V : array_like, shape (N, 2)
        Image keypoints, pixels, whose PnP optimum is ``(R, t)``.
    K : array_like, shape (3, 3)
        Intrinsics.
    R, t : array_like, shapes (3, 3), (3,)
        The PnP optimum for ``V`` (e.g. :func:`kpstudy.pose.pnp.solve_pnp`).
    scale : (sx, sy), optional
        Resize factors image → heatmap, ``u' = (u + 0.5)·sx − 0.5``. When given, v is
        in heatmap pixels (the columns for u are divided by sx, those for v by sy).

    Returns
    -------
    M : ndarray, shape (6, 2N)
        Row i, column 2k (2k+1): change of ξ_i (degrees or metres) per pixel of u_k
        (v_k).

    Raises
    ------
    ValueError
        Bad shapes or values, or a singular Hessian ``G_ξξ`` (degenerate keypoints),
        or ``(R, t)`` not a PnP optimum of ``V``.
    """
    P, V, K = _check_problem(P, V, K)
    R = _checks.rotation(R)
    t = _checks.float_array(t, "t", (3,))
    if scale is not None:
        sx, sy = _checks.positive(scale, "scale", (2,))
    xi = torch.from_numpy(np.concatenate([euler_from_matrix(R), t]))
    v = torch.from_numpy(V.reshape(-1))
    Pt, Kt = torch.tensor(P), torch.tensor(K)

    g = jacrev(reprojection_cost)(xi, v, Pt, Kt)
    H = hessian(reprojection_cost)(xi, v, Pt, Kt)
    H_xv = jacfwd(jacrev(reprojection_cost), argnums=1)(xi, v, Pt, Kt)  # (6, 2N)
    # Scale-free conditioning: columns of H in degrees and metres differ by orders.
    d = torch.sqrt(torch.clamp(H.diagonal(), min=1e-300))
    Hn = H / d[:, None] / d[None, :]
    if not torch.isfinite(Hn).all() or torch.linalg.cond(Hn) > 1e12:
        raise ValueError(
            "P: keypoints give a singular Hessian of the reprojection error "
            "(degenerate configuration); expected a well-posed PnP problem"
        )
    newton = torch.linalg.solve(H, g)
    motion = _keypoint_motion(Pt, Kt, xi, newton)
    if motion > OPTIMUM_TOL_PX:
        raise ValueError(
            f"R, t: expected the PnP optimum of V (one Newton step moves the keypoints by "
            f"{motion:.3g} px); pass the pose returned by solve_pnp(P, V, K)"
        )
    M = -torch.linalg.solve(H, H_xv).numpy()
    if scale is not None:
        M[:, 0::2] /= sx
        M[:, 1::2] /= sy
    return M


def _keypoint_motion(P, K, xi, step) -> float:
    """Largest reprojection displacement, pixels, caused by moving ξ by ``−step``."""

    def uv(x):
        return project_batch(P, matrix_from_euler_torch(x[:3]), x[3:], K)

    return float((uv(xi - step) - uv(xi)).abs().max())
