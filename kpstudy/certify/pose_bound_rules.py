"""The pose-bound method's decision rules: from keypoint regions to pose errors.

Given each keypoint's possible positions (its region's pixels, docs/design.md §4.11):

* :func:`linearised_bound`: the largest linearised pose error ``|M δ|`` over the product
  of the keypoints' deviation sets, exact for that product *of the linearisation* and
  separable per keypoint;
* :func:`enumerated_pose_error` (and ``enumerate_combinations()``, which also says
  which combination is farthest outside Ξ and which pixels take part in one outside):
  PnP on *every* combination of positions, in chunks of :data:`ENUMERATION_CHUNK`
  problems, exact for the argmax → PnP pipeline over the product;
* :func:`single_moves`: the moves of one keypoint, the others held, that alone take the
  pose outside Ξ.

Every PnP here is ``pnp_pose_errors()``: Levenberg–Marquardt from the nominal pose
(:func:`kpstudy.pose.pnp.solve_pnp_batch`), a pose that PnP flags as not valid counting
as outside Ξ (an ``inf`` error).

Units: keypoint positions ``(u, v)`` in image pixels (:func:`single_moves`: heatmap
pixels, converted with the resize factors); pose errors per axis ``|Δroll|, |Δpitch|,
|Δyaw|`` in degrees (wrapped) and ``|Δt_x|, |Δt_y|, |Δt_z|`` in metres; Ξ's half-widths
``eps`` (6,) in the same units.
"""

from __future__ import annotations

import math

import numpy as np

from kpstudy import _checks
from kpstudy.models.preprocess import to_image_pixels
from kpstudy.pose.geometry import euler_from_matrix, inside_tolerance, wrap_degrees
from kpstudy.pose.pnp import solve_pnp_batch

__all__ = [
    "ENUMERATION_CHUNK",
    "enumerated_pose_error",
    "linearised_bound",
    "single_moves",
]

#: PnP problems solved together by :func:`enumerated_pose_error` (bounds its memory: about
#: 1 KB per problem per keypoint in the solver).
ENUMERATION_CHUNK = 10**5


def pnp_pose_errors(seed, V, R, t) -> np.ndarray:
    """Pose errors ``(B, 6)`` of PnP (from the nominal pose) on keypoints ``V (B, K, 2)``;
    ``inf`` where PnP flags the pose as not valid (:class:`kpstudy.pose.pnp.PnPResult`), so that
    it never lies inside Ξ."""
    B = len(V)
    pose = solve_pnp_batch(
        seed.points_3d, V, seed.K, (np.broadcast_to(R, (B, 3, 3)), np.broadcast_to(t, (B, 3)))
    )
    errors = np.full((B, 6), np.inf)
    ok = pose.valid
    dr = wrap_degrees(euler_from_matrix(pose.R[ok]) - euler_from_matrix(R)[None])
    errors[ok] = np.concatenate([dr, np.abs(pose.t[ok] - t)], axis=1)
    return errors


def linearised_bound(M, deviations) -> tuple[np.ndarray, np.ndarray]:
    """Largest ``|M δ|`` per pose axis over the product of the keypoints' deviation sets.

    Parameters
    ----------
    M : array_like, shape (6, 2K)
        ``dξ/dv`` (degrees and metres per image pixel), columns ``u1, v1, u2, …``.
    deviations : sequence of K arrays, shape (n_k, 2)
        Possible deviations ``(δu, δv)`` of keypoint k from its ground truth, image pixels;
        ``n_k ≥ 1``.

    Returns
    -------
    bound : ndarray, shape (6,)
        ``max(Σ_k max_p M_k δ_p, −Σ_k min_p M_k δ_p)``: the exact maximum of ``|M δ|`` over
        the product (the sum separates per keypoint), degrees then metres.
    extremes : ndarray, shape (12, K)
        Per axis and sign (``+roll, −roll, +pitch, …``), the index into each keypoint's set
        that attains it: the corners for the nonlinear check.
    """
    M = np.asarray(M, dtype=np.float64)
    K = len(deviations)
    if M.shape != (6, 2 * K):
        raise ValueError(f"M: expected shape (6, {2 * K}) for {K} keypoints, got {M.shape}")
    hi, lo = np.zeros(6), np.zeros(6)
    extremes = np.zeros((12, K), dtype=np.int64)
    for k, d in enumerate(deviations):
        d = np.asarray(d, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 2 or len(d) == 0:
            raise ValueError(f"deviations[{k}]: expected shape (n >= 1, 2), got {d.shape}")
        values = M[:, 2 * k : 2 * k + 2] @ d.T  # (6, n_k)
        hi += values.max(1)
        lo += values.min(1)
        extremes[0::2, k] = values.argmax(1)
        extremes[1::2, k] = values.argmin(1)
    return np.maximum(hi, -lo), extremes


def enumerated_pose_error(seed, keypoints, R, t, *, chunk: int | None = None) -> np.ndarray:
    """Largest PnP pose error per axis over every combination of keypoint positions.

    Parameters
    ----------
    seed : kpstudy.certify.allocation_method.SeedImage
        Its ``points_3d (K, 3)`` (metres) and intrinsics ``K (3, 3)``.
    keypoints : sequence of K arrays, shape (n_k, 2)
        Possible ``(u, v)`` of keypoint k, image pixels; ``n_k ≥ 1``. The combinations are
        the ``Π n_k`` rows of their product.
    R, t : ndarray, shapes (3, 3) and (3,)
        Nominal pose: every PnP starts there, and the error is measured from it.
    chunk : int, optional
        Problems solved together (default :data:`ENUMERATION_CHUNK`), ≥ 1: the memory
        stays bounded whatever the number of combinations.

    Returns
    -------
    ndarray, shape (6,)
        ``max`` over the combinations of ``|Δroll|, |Δpitch|, |Δyaw|`` (degrees, wrapped)
        and ``|Δt_x|, |Δt_y|, |Δt_z|`` (metres); ``inf`` on every axis if PnP flags some
        combination's pose as not valid.
    """
    return enumerate_combinations(seed, keypoints, R, t, np.ones(6), chunk)[0]


def enumerate_combinations(seed, keypoints, R, t, eps, chunk=None) -> tuple:
    """:func:`enumerated_pose_error`, the combination (one index per keypoint) whose
    error is farthest outside ``eps (6,)`` (the largest ``max_i error_i / eps_i``) and,
    per keypoint, which of its pixels ``(n_k,)`` bool take part in a combination outside
    ``eps``."""
    chunk = ENUMERATION_CHUNK if chunk is None else chunk
    _checks.integer(chunk, "chunk", minimum=1)
    points = [np.asarray(p, dtype=np.float64) for p in keypoints]
    for k, p in enumerate(points):
        if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
            raise ValueError(f"keypoints[{k}]: expected shape (n >= 1, 2), got {p.shape}")
    sizes = tuple(len(p) for p in points)
    total = math.prod(sizes)
    worst, farthest, where = np.zeros(6), -1.0, 0
    involved = [np.zeros(n, dtype=bool) for n in sizes]
    for begin in range(0, total, int(chunk)):
        index = np.unravel_index(np.arange(begin, min(begin + int(chunk), total)), sizes)
        V = np.stack([p[i] for p, i in zip(points, index)], axis=1)  # (B, K, 2)
        errors = pnp_pose_errors(seed, V, R, t)
        worst = np.maximum(worst, errors.max(0))
        ratio = (errors / eps).max(1)
        if ratio.max() > farthest:
            farthest, where = float(ratio.max()), begin + int(ratio.argmax())
        outside = ~inside_tolerance(errors, eps)
        for mask, i in zip(involved, index):
            mask[i[outside]] = True
    return worst, np.array(np.unravel_index(where, sizes)), involved


def single_moves(seed, pixels, base, factors, R, t, eps) -> list[tuple[int, np.ndarray]]:
    """The possible moves of one keypoint that alone take the pose outside Ξ.

    Parameters
    ----------
    seed : kpstudy.certify.allocation_method.SeedImage
    pixels : sequence of K arrays, shape (n_k, 2)
        Possible heatmap pixels ``(u, v)`` of each keypoint.
    base : ndarray, shape (K, 2)
        Heatmap pixels ``(u, v)`` the other keypoints keep (the seed image's argmax).
    factors : pair
        :func:`kpstudy.models.preprocess.scale_factors` of the seed image and the heatmaps.
    R, t : nominal pose; eps : ndarray, shape (6,), Ξ's half-widths (degrees, metres).

    Returns
    -------
    list of (int, ndarray (2,))
        ``(k, pixel)`` with ``pixel ≠ base[k]`` in keypoint k's region whose pose (every
        other keypoint at ``base``) lies outside Ξ, farthest outside first (the largest
        ``max_i error_i / eps_i``).
    """
    base = np.asarray(base, dtype=np.float64)
    moves = [(k, p) for k, region in enumerate(pixels) for p in region if np.any(p != base[k])]
    if not moves:
        return []
    V = np.repeat(base[None], len(moves), 0)
    for row, (k, p) in enumerate(moves):
        V[row, k] = p
    errors = pnp_pose_errors(seed, to_image_pixels(V, factors), R, t)
    ratio = (errors / eps).max(1)
    order = [i for i in np.argsort(-ratio, kind="stable") if ratio[i] > 1]
    return [moves[i] for i in order]
