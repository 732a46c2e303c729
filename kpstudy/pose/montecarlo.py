"""Probabilistic soundness and completeness of a tolerance allocation (paper §6.2, §8.3).

For one image with ground-truth keypoints V (pixels), nominal pose (R, t) = PnP(V) and
allocated half-widths δV (the box HR):

* soundness — random *vertices* of HR added to V (``V̂ = V + A ⊙ δV``, A ∈ {±1}),
  PnP re-solved from the nominal pose; the fraction whose pose error lies in Ξ;
* completeness — pose errors δξ uniform in ``Ξ = {|δξ| ≤ ε}``, keypoints re-projected;
  the fraction whose keypoint errors lie in HR.

Both are vectorised over images and samples; each image draws from its own stream
``default_rng([seed, image_index])``, so results do not depend on chunking.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from kpstudy import _checks
from kpstudy.pose.allocation import allocate_many, allocation_scale
from kpstudy.pose.geometry import (
    euler_from_matrix_torch,
    inside_tolerance,
    matrix_from_euler_torch,
    project_batch,
    tolerance,
    wrap_degrees,
)
from kpstudy.pose.pnp import solve_pnp, solve_pnp_batch
from kpstudy.pose.sensitivity import pose_sensitivity

#: Stopping tolerance of the soundness PnP solves (pixels). Newton's last step is below
#: it, so the pose is within far less of its optimum; on 5e5 paper-like problems the
#: fractions equal those at 1e-7 bit for bit (1e-3 flips one sample) and the solves are
#: 15 % faster.
SOUNDNESS_TOL_PX = 1e-4


def probabilistic_soundness(
    P,
    V,
    K,
    R,
    t,
    dv,
    eps_r,
    eps_t,
    *,
    n_samples: int,
    seed: int,
    scale=None,
    chunk_images: int | None = None,
    compile: bool = False,
    tol_px: float = SOUNDNESS_TOL_PX,
) -> np.ndarray:
    """Fraction of random vertices of the allocated box whose PnP pose stays in Ξ.

    Parameters
    ----------
    P : array_like, shape (N, 3)
        Object keypoints, metres.
    V : array_like, shape (I, N, 2)
        Ground-truth keypoints of I images, image pixels.
    K : array_like, shape (3, 3) or (I, 3, 3)
        Intrinsics.
    R, t : array_like, shapes (I, 3, 3), (I, 3)
        Nominal poses, PnP on V.
    dv : array_like, shape (I, N, 2)
        Allocated half-widths, heatmap pixels if ``scale`` is given, else image pixels.
    eps_r, eps_t : array_like, shape (3,)
        Tolerances, degrees and metres.
    n_samples : int
        Vertices per image.
    seed : int
    scale : (sx, sy), optional
        Image → heatmap resize factors; ``dv`` is divided by them.
    chunk_images : int, optional
        Images solved together (default: about 64k PnP problems at a time).
    compile, tol_px :
        Passed to :func:`kpstudy.pose.pnp.solve_pnp_batch`.

    Returns
    -------
    ndarray, shape (I,)
        Per-image fraction in [0, 1]. A vertex whose PnP pose is not valid (a point behind
        the camera, a residual near the keypoints' spread: :class:`kpstudy.pose.pnp.PnPResult`)
        counts as outside Ξ.
    """
    P, V, K, R, t, dV, eps = _check_study(P, V, K, R, t, dv, eps_r, eps_t, n_samples, scale)
    I, N = V.shape[:2]
    out = np.empty(I)
    step = chunk_images or max(1, 65536 // n_samples)
    for lo in range(0, I, step):
        idx = np.arange(lo, min(lo + step, I))
        signs = np.stack([_rng(seed, i).choice([-1.0, 1.0], size=(n_samples, N, 2)) for i in idx])
        V_hat = V[idx, None] + signs * dV[idx, None]  # (c, S, N, 2)
        K_c, R_c, t_c = (np.repeat(a[idx], n_samples, axis=0) for a in (K, R, t))
        pose = solve_pnp_batch(
            P,
            torch.from_numpy(V_hat.reshape(-1, N, 2)),
            K_c,
            (R_c, t_c),
            compile=compile,
            tol_px=tol_px,
        )
        inside = _inside(pose.R, pose.t, torch.from_numpy(R_c), torch.from_numpy(t_c), eps)
        inside &= pose.valid  # a pose PnP flags (behind the camera, …) is never inside Ξ
        out[idx] = inside.reshape(len(idx), n_samples).double().mean(1).numpy()
    return out


def probabilistic_completeness(
    P, V, K, R, t, dv, eps_r, eps_t, *, n_samples: int, seed: int, scale=None
) -> np.ndarray:
    """Fraction of pose errors uniform in Ξ whose re-projected keypoints stay in the box.

    Parameters are those of :func:`probabilistic_soundness`.

    Returns
    -------
    ndarray, shape (I,)
        Per-image fraction in [0, 1].
    """
    P, V, K, R, t, dV, eps = _check_study(P, V, K, R, t, dv, eps_r, eps_t, n_samples, scale)
    I = V.shape[0]
    out = np.empty(I)
    Pt = torch.from_numpy(P)
    for i in range(I):
        dxi = torch.from_numpy(_rng(seed, i).uniform(-1.0, 1.0, (n_samples, 6)) * eps)
        e0 = euler_from_matrix_torch(torch.from_numpy(R[i]))
        R_s = matrix_from_euler_torch(e0 + dxi[:, :3])
        t_s = torch.from_numpy(t[i]) + dxi[:, 3:]
        V_s = project_batch(Pt, R_s, t_s, torch.from_numpy(K[i]))  # (S, N, 2)
        err = (V_s - torch.from_numpy(V[i])).abs()
        out[i] = (err <= torch.from_numpy(dV[i])).all(-1).all(-1).double().mean().item()
    return out


def soundness_completeness_table(
    P,
    V,
    K,
    *,
    kappas,
    alphas,
    n_samples: int,
    seed: int,
    scale=None,
    max_dv=None,
    w1: float = 1.0,
    w2: float = 5.0,
    compile: bool = False,
    progress: bool = False,
    workers: int = 1,
    tolerance_units: str = "heatmap",
) -> pd.DataFrame:
    """The paper's T-prob grid: allocate per image, then both Monte Carlo fractions.

    Parameters
    ----------
    P, V, K : see :func:`probabilistic_soundness`
        The nominal pose of each image is PnP on its ground-truth keypoints V.
    kappas, alphas : sequence of float
        Grid of scaling factors κ and tolerance factors α (ε = α·[10°, 10°, 10°, 4, 4, 20 m]).
    n_samples : int
        Samples per image and configuration.
    scale, max_dv, w1, w2 :
        Heatmap resize factors, tolerance cap (heatmap size) and allocation weights.
    compile, progress :
        Fuse the batched PnP (:func:`kpstudy.pose.pnp.solve_pnp_batch`); show a progress bar.
    workers : int
        Processes for the allocations of the whole grid
        (:func:`kpstudy.pose.allocation.allocate_many`).
    tolerance_units : {'heatmap', 'paper'}
        The reading of the tolerances (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`). Under
        ``'paper'`` the allocation and both fractions are in image pixels (the paper's
        computation) and ``soundness_true_units`` is the soundness of the same integer
        boxes read as heatmap pixels (divided by ``scale``), the boxes the verifier proves.

    Returns
    -------
    DataFrame
        One row per (κ, α): ``tolerance_units``, ``soundness``, ``completeness`` (pooled
        over images), ``soundness_true_units``, ``soundness_min_image``, ``mean_dv``,
        ``images``, ``samples``.
    """
    V = _checks.float_array(V, "V", (None, None, 2))
    I = V.shape[0]
    K = _per_image(K, I)
    poses = [solve_pnp(P, V[i], K[i]) for i in range(I)]
    bad = [i for i, p in enumerate(poses) if not p.valid]
    if bad:
        raise ValueError(
            f"V: PnP on the keypoints of image {bad[0]} gives no valid nominal pose "
            f"(smallest depth {poses[bad[0]].min_depth:.4g} m, "
            f"residual {poses[bad[0]].rms_px:.3g} px)"
        )
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    reading = allocation_scale(tolerance_units, scale)
    M = [pose_sensitivity(P, V[i], K[i], R[i], t[i], scale=reading) for i in range(I)]
    rows = []
    grid = [(kappa, alpha) for kappa in kappas for alpha in alphas]
    problems = [(m, *np.split(tolerance(a), 2), k) for k, a in grid for m in M]
    allocations = allocate_many(problems, workers=workers, w1=w1, w2=w2, max_dv=max_dv)
    for c, (kappa, alpha) in enumerate(
        tqdm(grid, desc="T-prob (kappa, alpha)", disable=not progress)
    ):
        eps_r, eps_t = np.split(tolerance(alpha), 2)
        dv = np.stack([a.dv for a in allocations[c * I : (c + 1) * I]])
        args = (P, V, K, R, t, dv, eps_r, eps_t)
        s = probabilistic_soundness(
            *args, n_samples=n_samples, seed=seed, scale=reading, compile=compile
        )
        c = probabilistic_completeness(*args, n_samples=n_samples, seed=seed, scale=reading)
        true = s
        if reading is None and scale is not None:  # the same boxes in heatmap pixels
            true = probabilistic_soundness(
                *args, n_samples=n_samples, seed=seed, scale=scale, compile=compile
            )
        rows.append(
            dict(
                tolerance_units=tolerance_units,
                kappa=kappa,
                alpha=alpha,
                soundness=s.mean(),
                completeness=c.mean(),
                soundness_true_units=true.mean(),
                soundness_min_image=s.min(),
                mean_dv=dv.mean(),
                images=I,
                samples=I * n_samples,
            )
        )
    return pd.DataFrame(rows)


def _inside(R_hat, t_hat, R, t, eps) -> torch.Tensor:
    """Pose error inside Ξ, per row: ``(B,)`` bool."""
    dr = wrap_degrees(euler_from_matrix_torch(R_hat) - euler_from_matrix_torch(R))
    dt = (t_hat - t).abs()
    return inside_tolerance(torch.cat([dr, dt], -1), eps)


def _rng(seed: int, image: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(image)])


def _per_image(K, I: int) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 3):
        K = np.repeat(K[None], I, axis=0)
    K = _checks.float_array(K, "K", (I, 3, 3))
    for k in K:
        _checks.intrinsics(k)
    return K


def _check_study(P, V, K, R, t, dv, eps_r, eps_t, n_samples, scale):
    P = _checks.float_array(P, "P", (None, 3))
    N = P.shape[0]
    V = _checks.float_array(V, "V", (None, N, 2))
    I = V.shape[0]
    K = _per_image(K, I)
    R = _checks.float_array(R, "R", (I, 3, 3))
    t = _checks.float_array(t, "t", (I, 3))
    dv = _checks.float_array(dv, "dv", (I, N, 2))
    if np.any(dv < 0):
        raise ValueError("dv: expected non-negative tolerances")
    eps = np.concatenate(
        [_checks.positive(eps_r, "eps_r", (3,)), _checks.positive(eps_t, "eps_t", (3,))]
    )
    if int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples: expected a positive integer, got {n_samples}")
    if scale is not None:
        dv = dv / _checks.positive(scale, "scale", (2,))
    return P, V, K, R, t, dv, eps
