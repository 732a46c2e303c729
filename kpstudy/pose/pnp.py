"""Perspective-n-Point: OpenCV for single problems, batched damped Newton in torch.

Both minimise the same reprojection least squares
``G(R, t; V) = Σ_k ||π(K (R p_k + t)) − v_k||²`` (pixels², no lens distortion), so from
the same starting pose they reach the same local optimum. :func:`solve_pnp` is the
reference (SQPnP, a globally optimal solver, then OpenCV's LM refinement);
:func:`solve_pnp_batch` refines many problems at once from given initial poses, which
is what the Monte Carlo study needs (millions of problems near a known pose). It uses
the exact Hessian with Levenberg–Marquardt damping: on the large-residual problems of
the Monte Carlo study (keypoints moved by tens of pixels) Gauss–Newton, as in OpenCV,
crawls along the nearly flat bas-relief direction of an overhead view; Newton converges
in about 8 iterations instead of 38 and reaches a cost never above OpenCV's.

Both return a :class:`PnPResult`, which unpacks as ``R, t`` and says whether each pose can
be trusted (``valid``): every object point in front of the camera (cheirality), finite,
keypoints that are not collinear, and a root-mean-square reprojection residual no larger
than ``max_rms_px``. A pose that is not valid must never be counted as inside Ξ.
"""

from __future__ import annotations

import functools
import math
import numbers

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from kpstudy import _checks

#: Default residual limit of a valid pose, a fraction of the keypoints' RMS spread about
#: their centroid. The degenerate pose that shrinks the object to one point far away has a
#: residual equal to the spread, and a solve that runs off towards it (t → ∞) nears it
#: from below (measured: 0.993–1 − 3e-8 at 10²–10⁸ times the true distance); a pose above
#: the limit explains under 2 % of the keypoints' variance. Monte Carlo vertices stay
#: below 0.75 at α = 2 and 0.9 at α = 5; a two-epoch CNN's argmax keypoints reach 0.96.
RESIDUAL_SPREAD_LIMIT = 0.99

#: OpenCV LM termination: iterations, and the step size below which it stops.
_CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


class PnPResult(tuple):
    """A PnP solution: unpacks as ``R, t`` (a 2-tuple) and carries its diagnostics.

    Attributes
    ----------
    R : (3, 3) or (B, 3, 3)
        Rotation, object → camera.
    t : (3,) or (B, 3)
        Translation, metres.
    valid : bool or (B,) bool
        The pose can be trusted: finite, every object point at a depth > 0 (in front of
        the camera), keypoints not collinear, and ``rms_px <= max_rms_px``. Where it is
        False, ``R`` and ``t`` are whatever the solver stopped at and mean nothing.
    rms_px : float or (B,)
        Root-mean-square reprojection residual ``sqrt(G / N)``, pixels.
    min_depth : float or (B,)
        Smallest depth ``(R p + t)_z`` over the object points, metres.

    Single problems (:func:`solve_pnp`) give Python scalars; batches
    (:func:`solve_pnp_batch`) give arrays of the type of ``R``.
    """

    def __new__(cls, R, t, valid, rms_px, min_depth):
        self = super().__new__(cls, (R, t))
        self.valid, self.rms_px, self.min_depth = valid, rms_px, min_depth
        return self

    @property
    def R(self):
        return self[0]

    @property
    def t(self):
        return self[1]

    def __reduce__(self):
        return type(self), (self[0], self[1], self.valid, self.rms_px, self.min_depth)

    def __repr__(self) -> str:
        return f"PnPResult(R={self[0]!r}, t={self[1]!r}, valid={self.valid!r})"


def _check_problem(P, V, K) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    P = _checks.float_array(P, "P", (None, 3))
    if P.shape[0] < 4:
        raise ValueError(f"P: expected at least 4 points, got {P.shape[0]}")
    V = _checks.float_array(V, "V", (P.shape[0], 2))
    K = _checks.intrinsics(K)
    for name, X in (("P", P), ("V", V)):
        s = np.linalg.svd(X - X.mean(0), compute_uv=False)
        if s[1] <= 1e-9 * max(s[0], 1e-300):
            raise ValueError(f"{name}: expected points that are not collinear")
    return np.ascontiguousarray(P), np.ascontiguousarray(V), K  # OpenCV wants contiguous rows


def _check_pose(init, P, name: str = "init") -> tuple[np.ndarray, np.ndarray]:
    try:
        R0, t0 = init
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a pair (R (3, 3), t (3,))") from exc
    R0, t0 = _checks.rotation(R0, f"{name}[0]"), _checks.float_array(t0, f"{name}[1]", (3,))
    depth = float((P @ R0[2] + t0[2]).min())
    if not depth > 0:
        raise ValueError(
            f"{name}: expected a pose with every point in front of the camera (depth > 0), "
            f"got a point at depth {depth:.4g} m"
        )
    return R0, t0


def _check_max_rms(max_rms_px):
    if max_rms_px is None:
        return None
    if not _is_real(max_rms_px) or not max_rms_px > 0:
        raise ValueError(f"max_rms_px: expected a number > 0 (pixels) or None, got {max_rms_px!r}")
    return float(max_rms_px)


def _is_real(x) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _positive_int(x, name: str) -> int:
    if isinstance(x, bool) or not isinstance(x, numbers.Integral) or x < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {x!r}")
    return int(x)


def _spread(V: np.ndarray) -> float:
    """RMS distance (pixels) of keypoints ``V (N, 2)`` to their centroid."""
    return float(np.sqrt(((V - V.mean(0)) ** 2).sum(-1).mean()))


def solve_pnp(P, V, K, init=None, *, max_rms_px=None) -> PnPResult:
    """Pose from 3D–2D correspondences with OpenCV.

    Parameters
    ----------
    P : array_like, shape (N, 3)
        Object points in metres, N ≥ 4, not collinear.
    V : array_like, shape (N, 2)
        Their pixel coordinates ``(u, v)``.
    K : array_like, shape (3, 3)
        Pinhole intrinsics.
    init : (R (3, 3), t (3,)), optional
        Starting pose, a rotation and a translation (metres) that puts every point in
        front of the camera. Without it, SQPnP finds the global optimum first.
    max_rms_px : float, optional
        Largest root-mean-square reprojection residual (pixels) of a valid pose: set it
        from the keypoints' noise (a residual far above it means PnP explains nothing).
        Default: :data:`RESIDUAL_SPREAD_LIMIT` × the keypoints' RMS spread about their
        centroid (the spread is the residual of the degenerate pose that shrinks the
        object to one point far away).

    Returns
    -------
    PnPResult
        Unpacks as ``R (3, 3), t (3,)``: the pose after Levenberg–Marquardt refinement
        (``cv2.solvePnPRefineLM``). ``.valid`` (bool) is False for a pose with a point
        behind the camera (depth ≤ 0), a non-finite pose or a residual above
        ``max_rms_px``; ``.rms_px`` and ``.min_depth`` (metres) say why.

    Examples
    --------
    >>> R, t = solve_pnp(P, project(P, R_true, t_true, K), K)  # doctest: +SKIP
    """
    P, V, K = _check_problem(P, V, K)
    limit = _check_max_rms(max_rms_px)
    if init is None:
        try:
            ok, rvec, tvec = cv2.solvePnP(P, V, K, None, flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error as exc:  # e.g. SQPnP's variance threshold on clustered points
            raise ValueError(f"V: OpenCV's SQPnP rejected these keypoints ({exc.err})") from exc
        if not ok:
            raise RuntimeError("solve_pnp: SQPnP found no pose for these correspondences")
    else:
        R0, t0 = _check_pose(init, P)
        rvec, tvec = cv2.Rodrigues(R0)[0], t0.reshape(3, 1).copy()
    rvec, tvec = cv2.solvePnPRefineLM(P, V, K, None, rvec, tvec, criteria=_CV_CRITERIA)
    R, t = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
    X = P @ R.T + t  # camera frame (N, 3)
    min_depth = float(X[:, 2].min())
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = X[:, :2] / X[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    rms = float(np.sqrt(((uv - V) ** 2).sum(-1).mean()))
    limit = RESIDUAL_SPREAD_LIMIT * _spread(V) if limit is None else limit
    finite = bool(np.isfinite(R).all() and np.isfinite(t).all())
    valid = finite and min_depth > 0 and rms <= limit
    return PnPResult(R, t, bool(valid), rms, min_depth)


def solve_pnp_batch(
    P,
    V,
    K,
    init,
    *,
    max_iter: int = 100,
    tol_px: float = 1e-7,
    chunk: int = 4096,
    compile: bool = False,
    max_rms_px=None,
) -> PnPResult:
    """Refine many PnP problems at once with damped Newton (torch, float64).

    Parameters
    ----------
    P : array_like or Tensor, shape (N, 3)
        Object points in metres, shared by all problems; N ≥ 4, not collinear.
    V : array_like or Tensor, shape (B, N, 2)
        Pixel coordinates, one problem per batch row, finite.
    K : array_like or Tensor, shape (3, 3) or (B, 3, 3)
        Intrinsics.
    init : (R, t) with R (3, 3) or (B, 3, 3) and t (3,) or (B, 3)
        Starting poses (e.g. the nominal pose of a Monte Carlo study): rotations (to
        1e-6) and translations (metres) that put every point in front of the camera.
    max_iter : int
        Most LM iterations, ≥ 1.
    tol_px : float
        A problem has converged when its update moves the keypoints by less than
        ``tol_px`` pixels (root mean square, to first order: ``δᵀ JᵀJ δ ≤ N tol_px²``);
        finite, ≥ 0.
    chunk : int
        Problems iterated together, ≥ 1 (bounds the memory: about 1 KB per problem per
        point); converged problems leave the working set and new ones join it.
    compile : bool
        Fuse the iteration with ``torch.compile`` (a C++ compiler is needed; measured 3.8×
        faster on 1e5 problems here, after a one-off compilation of about 10 s).
    max_rms_px : float, optional
        Largest RMS reprojection residual (pixels) of a valid pose, as in
        :func:`solve_pnp`; default: :data:`RESIDUAL_SPREAD_LIMIT` × each problem's RMS
        keypoint spread about its centroid.

    Returns
    -------
    PnPResult
        Unpacks as ``R (B, 3, 3), t (B, 3)``; ``.valid (B,)`` bool flags each problem
        whose pose can be trusted (finite, every point at depth > 0, its keypoints not
        collinear, residual ≤ ``max_rms_px``), with ``.rms_px (B,)`` (pixels) and
        ``.min_depth (B,)`` (metres). Poses whose ``valid`` is False mean nothing and must
        never count as inside Ξ. Tensors if ``V`` is a tensor, numpy arrays otherwise.
        The update is on the left,
        ``R ← exp([ω]×) R``; the step solves ``(∇²G + μ diag(JᵀJ)) δ = −∇G`` with the
        exact Hessian where that matrix is positive definite, Gauss–Newton's ``JᵀJ``
        elsewhere, and Marquardt's rule for μ. Each problem keeps its own damping and
        stops on its own.

    Examples
    --------
    >>> R, t = solve_pnp_batch(P, V_noisy, K, (R_nominal, t_nominal))  # doctest: +SKIP
    """
    max_iter = _positive_int(max_iter, "max_iter")
    chunk = _positive_int(chunk, "chunk")
    if not _is_real(tol_px) or not (math.isfinite(tol_px) and tol_px >= 0):
        raise ValueError(f"tol_px: expected a finite number >= 0 (pixels), got {tol_px!r}")
    limit = _check_max_rms(max_rms_px)
    as_numpy = not isinstance(V, torch.Tensor)
    V = _tensor(V, "V", 3)
    if V.shape[-1] != 2 or V.shape[1] < 4:
        raise ValueError(f"V: expected shape (B, N, 2) with N >= 4, got {tuple(V.shape)}")
    B, N = V.shape[:2]
    P = _tensor(P, "P", 2)
    if P.shape != (N, 3):
        raise ValueError(f"P: expected shape ({N}, 3) to match V, got {tuple(P.shape)}")
    s = torch.linalg.svdvals(P - P.mean(0))
    if s[1] <= 1e-9 * max(float(s[0]), 1e-300):
        raise ValueError("P: expected points that are not collinear")
    K = _tensor(K, "K", (2, 3)).expand(B, 3, 3)
    pattern = torch.stack([K[:, 0, 0], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2]], -1)
    if not torch.equal(K, _intrinsics_matrix(pattern)) or (pattern[:, [0, 2]] <= 0).any():
        raise ValueError("K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    R, t = _check_batch_init(init, P, B)
    step, terms = _compiled() if compile else (_lm_step, _normal_equations)

    R_out, t_out = torch.empty(B, 3, 3, dtype=torch.float64), torch.empty(B, 3, dtype=torch.float64)
    # A working set of at most `chunk` problems, batch last (structure of arrays): it is
    # topped up with new problems as others converge, so the slow few never iterate alone.
    work, fed = None, 0
    while True:
        size = 0 if work is None else work[0].numel()
        if fed < B and size <= chunk // 2:
            take = slice(fed, min(fed + chunk - size, B))
            fresh = _initial_state(terms, P, K[take], V[take], R[take], t[take], fed)
            work = fresh if work is None else tuple(torch.cat(x, -1) for x in zip(work, fresh))
            fed = take.stop
        if work is None or work[0].numel() == 0:
            break
        index, iters, intr, Vu, Vv, *state = work
        state = step(P, intr, Vu, Vv, *state, N * tol_px**2)
        iters = iters + 1
        work = (index, iters, intr, Vu, Vv, *state)
        done = ~state[-1] | (iters >= max_iter)
        n_done = int(done.sum())
        if n_done and (4 * n_done >= done.numel() or fed == B):
            R_out[index[done]] = state[0][..., done].permute(2, 0, 1)
            t_out[index[done]] = state[1][:, done].T
            work = tuple(x[..., ~done] for x in work)
    valid, rms, depth = _diagnostics(P, K, V, R_out, t_out, limit, chunk)
    out = (R_out, t_out, valid, rms, depth)
    if as_numpy:
        out = tuple(x.numpy() for x in out)
    return PnPResult(*out)


def _check_batch_init(init, P, B: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial rotations ``(B, 3, 3)`` and translations ``(B, 3)`` of a batch, checked:
    rotation matrices (to 1e-6) that put every point of ``P`` in front of the camera."""
    try:
        R0, t0 = init
    except (TypeError, ValueError) as exc:
        raise ValueError("init: expected a pair (R (3, 3) or (B, 3, 3), t (3,) or (B, 3))") from exc
    R0, t0 = _tensor(R0, "init[0]", (2, 3)), _tensor(t0, "init[1]", (1, 2))
    if R0.shape[-2:] != (3, 3) or (R0.ndim == 3 and len(R0) != B):
        raise ValueError(f"init[0]: expected shape (3, 3) or ({B}, 3, 3), got {tuple(R0.shape)}")
    if t0.shape[-1] != 3 or (t0.ndim == 2 and len(t0) != B):
        raise ValueError(f"init[1]: expected shape (3,) or ({B}, 3), got {tuple(t0.shape)}")
    R, t = R0.expand(B, 3, 3), t0.expand(B, 3)
    Rb = R0.reshape(-1, 3, 3)
    off = (Rb @ Rb.mT - torch.eye(3, dtype=Rb.dtype)).abs().amax((-2, -1))
    bad = (off > 1e-6) | (torch.linalg.det(Rb) <= 0)
    if bad.any():
        where = f" (problem {int(bad.nonzero()[0, 0])})" if R0.ndim == 3 else ""
        raise ValueError(f"init[0]: expected rotation matrices (orthonormal, det +1){where}")
    depth = (R[:, 2, :] @ P.T + t[:, 2:]).amin(-1) if B else torch.ones(0)  # (B,)
    if not (depth > 0).all():
        i = int((depth <= 0).nonzero()[0, 0])
        raise ValueError(
            "init: expected poses with every point in front of the camera (depth > 0), "
            f"got a point at depth {float(depth[i]):.4g} m in problem {i}"
        )
    return R, t


def _diagnostics(P, K, V, R, t, limit, chunk: int):
    """Per problem: valid ``(B,)`` bool, RMS residual ``(B,)`` (pixels) and smallest depth
    ``(B,)`` (metres) of poses ``R (B, 3, 3)``, ``t (B, 3)``, ``chunk`` problems at a time."""
    B = len(V)
    valid = torch.empty(B, dtype=torch.bool)
    rms, depth = torch.empty(B, dtype=torch.float64), torch.empty(B, dtype=torch.float64)
    for lo in range(0, B, chunk):
        c = slice(lo, min(lo + chunk, B))
        X = torch.einsum("nj,bij->bni", P, R[c]) + t[c, None, :]  # (b, N, 3) camera frame
        f = torch.stack([K[c, 0, 0], K[c, 1, 1]], -1)[:, None, :]
        uv = X[..., :2] / X[..., 2:] * f + K[c, None, :2, 2]
        rms[c] = ((uv - V[c]) ** 2).sum(-1).mean(-1).sqrt()
        depth[c] = X[..., 2].amin(-1)
        Vc = V[c] - V[c].mean(1, keepdim=True)
        spread = (Vc**2).sum(-1).mean(-1).sqrt()
        s = torch.linalg.svdvals(Vc)  # (b, 2), descending
        scale = V[c].abs().amax((1, 2)) + 1.0  # rounding in Vc is ~1e-16 of this
        collinear = s[:, 1] <= 1e-9 * torch.maximum(s[:, 0], scale)  # or all at one point
        finite = torch.isfinite(R[c]).all(-1).all(-1) & torch.isfinite(t[c]).all(-1)
        bound = RESIDUAL_SPREAD_LIMIT * spread if limit is None else limit
        valid[c] = finite & (depth[c] > 0) & ~collinear & (rms[c] <= bound)
    return valid, rms, depth


def _intrinsics_matrix(f):
    """``(B, 3, 3)`` pinhole matrices from ``(B, 4)`` rows ``[fx, cx, fy, cy]``."""
    zero, one = torch.zeros_like(f[:, 0]), torch.ones_like(f[:, 0])
    rows = [[f[:, 0], zero, f[:, 1]], [zero, f[:, 2], f[:, 3]], [zero, zero, one]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def _initial_state(terms, P, K, V, R, t, first: int) -> tuple:
    """LM state of problems ``first, first + 1, …`` (batch last): global index, iteration
    count, intrinsics ``[fx, cx, fy, cy]``, keypoints, pose, Newton terms, damping, active."""
    intr = torch.stack([K[:, 0, 0], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2]])
    Vu, Vv = V[:, :, 0].T.contiguous(), V[:, :, 1].T.contiguous()
    Rc, tc = R.permute(1, 2, 0).contiguous(), t.T.contiguous()
    H, S, g, cost = terms(P, intr, Rc, tc, Vu, Vv)
    index = torch.arange(first, first + cost.numel())
    mu = torch.full_like(cost, 1e-3)
    active = torch.ones_like(cost, dtype=torch.bool)
    return (index, torch.zeros_like(index), intr, Vu, Vv, Rc, tc, H, S, g, cost, mu, active)


def _normal_equations(P, intr, R, t, Vu, Vv):
    """Newton terms of the reprojection cost ``½ Σ r²``, batch last.

    ``P (N, 3)``, ``intr (4, B)`` = [fx, cx, fy, cy], ``R (3, 3, B)``, ``t (3, B)``,
    ``Vu, Vv (N, B)``. Derivatives are w.r.t. ``ξ = [ω, t]`` with the left rotation
    increment ``R ← exp([ω]×) R``. Returns the 21 upper-triangular entries of ``JᵀJ``
    ``(21, B)`` and of the residual curvature ``S = Σ r ∇²r`` ``(21, B)`` (the exact
    Hessian is ``JᵀJ + S``), the gradient ``Jᵀr`` ``(6, B)`` and ``Σ r²`` ``(B,)``.
    """
    fx, cx, fy, cy = intr
    w = torch.einsum("nj,ijb->inb", P, R)  # R p, (3, N, B)
    wx, wy, wz = w[0], w[1], w[2]
    iz = 1.0 / (wz + t[2])
    x, y = (wx + t[0]) * iz, (wy + t[1]) * iz
    ru = fx * x + cx - Vu
    rv = fy * y + cy - Vv
    zero = torch.zeros_like(iz)
    # d(x, y)/dξ for the normalised image point (x, y) = (X/Z, Y/Z); dX/dω_a = e_a × w.
    Jx = [-x * wy * iz, (wz + x * wx) * iz, -wy * iz, iz, zero, -x * iz]
    Jy = [(-wz - y * wy) * iz, y * wx * iz, wx * iz, zero, iz, -y * iz]
    Ju = [fx * a for a in Jx]
    Jv = [fy * b for b in Jy]
    H = [(Ju[i] * Ju[j] + Jv[i] * Jv[j]).sum(0) for i in range(6) for j in range(i, 6)]
    g = [(Ju[i] * ru + Jv[i] * rv).sum(0) for i in range(6)]
    # S = Σ (r_u fx ∇²x + r_v fy ∇²y), from the quotient rule with
    # d²X_k/dω_a dω_b = ½(δ_kb w_a + δ_ka w_b) − δ_ab w_k (zero in the other blocks).
    pu, pv = fx * ru * iz, fy * rv * iz
    c = [pu, pv, -(pu * x + pv * y)]
    cw = c[0] * wx + c[1] * wy + c[2] * wz
    q = [pu * a + pv * b for a, b in zip(Jx, Jy)]
    dZ = [wy, -wx, None, None, None, torch.ones_like(iz)]  # dZ/dξ
    S = []
    for a in range(6):
        for b in range(a, 6):
            s = zero
            if b < 3:
                s = 0.5 * (c[b] * w[a] + c[a] * w[b]) - (cw if a == b else zero)
            if dZ[b] is not None:
                s = s - q[a] * dZ[b]
            if dZ[a] is not None:
                s = s - q[b] * dZ[a]
            S.append(s.sum(0))
    return torch.stack(H), torch.stack(S), torch.stack(g), (ru * ru + rv * rv).sum(0)


_UPPER = {(i, j): n for n, (i, j) in enumerate((i, j) for i in range(6) for j in range(i, 6))}


def _symmetric(H):
    """6×6 nested list of ``(B,)`` tensors from 21 upper-triangular rows ``(21, B)``."""
    return [[H[_UPPER[min(i, j), max(i, j)]] for j in range(6)] for i in range(6)]


def _cholesky_solve(A, g):
    """``−A⁻¹ g`` for SPD 6×6 ``A`` (nested lists of ``(B,)``) → ``(6, B)``, and whether
    every pivot was positive ``(B,)``."""
    L = [[None] * 6 for _ in range(6)]
    ok = torch.ones_like(g[0], dtype=torch.bool)
    for j in range(6):
        d = A[j][j] - sum((L[j][k] * L[j][k] for k in range(j)), torch.zeros_like(g[0]))
        ok = ok & (d > 0)
        L[j][j] = d.clamp_min(1e-300).sqrt()
        for i in range(j + 1, 6):
            off = A[i][j] - sum((L[i][k] * L[j][k] for k in range(j)), torch.zeros_like(g[0]))
            L[i][j] = off / L[j][j]
    z = [None] * 6
    for i in range(6):
        z[i] = -g[i] - sum((L[i][k] * z[k] for k in range(i)), torch.zeros_like(g[0]))
        z[i] = z[i] / L[i][i]
    x = [None] * 6
    for i in reversed(range(6)):
        x[i] = z[i] - sum((L[k][i] * x[k] for k in range(i + 1, 6)), torch.zeros_like(g[0]))
        x[i] = x[i] / L[i][i]
    return torch.stack(x), ok


def _damped_step(H, S, g, mu):
    """The LM step ``−(∇²G + μ D)⁻¹ Jᵀr`` with ``D = diag(JᵀJ)``, ``(6, B)``.

    The exact Hessian ``JᵀJ + S`` (Newton: fast on large residuals, where Gauss–Newton
    crawls along the flat bas-relief direction) where its damped form is positive
    definite, the Gauss–Newton matrix ``JᵀJ`` elsewhere.
    """
    A_gn, A_s = _symmetric(H), _symmetric(S)
    damp = [mu * A_gn[i][i].clamp_min(1e-12) for i in range(6)]
    A_gn = [[A_gn[i][j] + (damp[i] if i == j else 0.0) for j in range(6)] for i in range(6)]
    A_newton = [[A_gn[i][j] + A_s[i][j] for j in range(6)] for i in range(6)]
    step_n, ok = _cholesky_solve(A_newton, g)
    step_gn, _ = _cholesky_solve(A_gn, g)
    return torch.where(ok, step_n, step_gn)


def _lm_step(P, intr, Vu, Vv, R, t, H, S, g, cost, mu, active, step_tol2):
    """One LM iteration for every problem of a working set; returns ``(R, t, H, S, g,
    cost, mu, active)`` updated (batch last)."""
    step = _damped_step(H, S, g, mu)
    dR = axis_angle_to_rotation_matrix(step[:3].T).permute(1, 2, 0)  # (3, 3, B)
    R_new = (dR[:, :, None, :] * R[None, :, :, :]).sum(1)  # dR @ R per problem
    t_new = t + step[3:]
    H_new, S_new, g_new, cost_new = _normal_equations(P, intr, R_new, t_new, Vu, Vv)
    better = (cost_new < cost) & active
    A = _symmetric(H)
    moved2 = sum(step[i] * A[i][j] * step[j] for i in range(6) for j in range(6))  # |Jδ|²
    small = moved2 <= step_tol2
    mu = torch.where(better, mu / 10.0, mu * 10.0).clamp(1e-12, 1e12)
    active = active & ~(small | (mu >= 1e12))
    keep = lambda new, old: torch.where(better, new, old)  # noqa: E731
    return (
        keep(R_new, R),
        keep(t_new, t),
        keep(H_new, H),
        keep(S_new, S),
        keep(g_new, g),
        keep(cost_new, cost),
        mu,
        active,
    )


@functools.cache
def _compiled():
    """The fused (torch.compile) LM step and Newton terms, compiled once per process."""
    return torch.compile(_lm_step, dynamic=True), torch.compile(_normal_equations, dynamic=True)


def _tensor(x, name: str, ndim) -> torch.Tensor:
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if isinstance(x, torch.Tensor):
        x = x.to(torch.float64)
    else:
        x = torch.from_numpy(np.array(x, dtype=np.float64))  # a writable copy
    if x.ndim not in ndims:
        raise ValueError(
            f"{name}: expected {' or '.join(map(str, ndims))} dimensions, "
            f"got shape {tuple(x.shape)}"
        )
    if not torch.isfinite(x).all():
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return x
