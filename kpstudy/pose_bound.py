"""A certified pose-error bound per seed image, from where each keypoint can go.

The paper allocates keypoint tolerances *before* verification and asks the verifier to
keep each keypoint in its cell; this module asks the verifier *where* each keypoint can
go and bounds the pose error from that (DESIGN.md §4, issue 7):

1. :func:`kpstudy.verify.reachable_argmax` on the backbone's heatmaps (``stride`` 1: the
   argmax head's own pixels; an odd ``stride`` > 1 pools ``stride × stride`` cells around
   the rounded ground truth, like the paper's proxy) gives each keypoint's possible pixels;
2. each possible pixel is a keypoint deviation ``δ = v − v_gt`` in image pixels;
3. the linearised pose error ``δξ = M δ`` (``M = dξ/dv`` in image pixels) is bounded per
   axis by ``max |Σ_k M_k δ_k|`` over the product of the keypoints' pixel sets, which is
   exact for that product and separable per keypoint (:func:`linearised_bound`); it is
   never above the triangle-inequality bound ``Σ_j |M_ij| max |δ_j|``;
4. PnP is re-solved at the extreme combinations of region pixels (the nonlinear check);
5. the argmax → PnP pose is computed at every witness image of the reachability search:
   one outside Ξ is a real counterexample.

Verdict: ``violated`` when a witness image's argmax pose lies outside Ξ, else ``holds``
when ``κ · bound ≤ ε`` on every axis, else ``unknown``. ``holds`` covers the argmax head
and the linearised PnP; the nonlinear check says how far the linearisation is off.
"""

from __future__ import annotations

import hashlib
import time

import numpy as np
import torch

from kpstudy.geometry import euler_from_matrix, wrap_degrees
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.proxy import build_proxy
from kpstudy.pnp import solve_pnp_batch
from kpstudy.pooling import cell_bounds, keypoint_pooling, num_cells
from kpstudy.preprocess import scale_factors, to_image_pixels, to_input_pixels
from kpstudy.verify import reachable_argmax

__all__ = ["linearised_bound", "pose_bound", "region_pixels"]


def region_pixels(regions, pooling, heatmap_size: int) -> list[np.ndarray]:
    """Heatmap pixels ``(n_k, 2)`` as ``(u, v)`` of each keypoint's possible cells.

    ``pooling`` is the (horizontal, vertical) :class:`kpstudy.pooling.PoolParams` pair of
    each keypoint that the regions' proxy used; a cell contributes all its real pixels.
    """
    out = []
    for k, (horizontal, vertical) in enumerate(pooling):
        n_h = num_cells(horizontal, heatmap_size)
        pixels = set()
        for cell in regions.possible[k].tolist():
            v0, v1 = cell_bounds(cell // n_h, vertical, heatmap_size)
            u0, u1 = cell_bounds(cell % n_h, horizontal, heatmap_size)
            pixels.update((u, v) for u in range(u0, u1 + 1) for v in range(v0, v1 + 1))
        out.append(np.array(sorted(pixels), dtype=np.float64).reshape(-1, 2))
    return out


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


def pose_bound(
    backbone,
    hull,
    seed,
    R,
    t,
    M,
    eps,
    *,
    kappa: float = 1.0,
    stride: int = 1,
    timeout: float = 10.0,
    method: str = "forward",
    random_corners: int = 64,
    sample_seed: int = 0,
) -> dict:
    """Certify the argmax → PnP pose error of every image of ``hull`` (one seed image).

    Parameters
    ----------
    backbone : nn.Module
        Heatmap backbone with ``heatmap_size`` and ``input_size``.
    hull : ConvexHull
        Model inputs ``(n+1, 3, s, s)``, the seed first.
    seed : kpstudy.certify.SeedImage
    R, t : ndarray
        Nominal pose (PnP on the ground truth).
    M : ndarray, shape (6, 2K)
        ``dξ/dv`` at that pose in *image* pixels.
    eps : ndarray, shape (6,)
        Ξ's half-widths, degrees then metres.
    kappa : float
        The bound must satisfy ``κ · bound ≤ ε``.
    stride : int
        Odd cell side in heatmap pixels; 1 certifies the argmax pixel itself.
    timeout : float
        Seconds for :func:`kpstudy.verify.reachable_argmax`. Its regions depend on the hull
        only, so the instances of one hull (their α, κ) share one search; ``pb_time``
        counts the search in full for each.
    method : {'forward', 'zonotope', 'ibp'}
        Its bounds: ``'zonotope'`` gives far smaller regions on a trained CNN, at tens
        of seconds per node on 2 CPU cores (``'forward'``: a fraction of a second).
    random_corners : int
        Random combinations of region pixels re-solved in the nonlinear check, besides the
        12 extreme ones.
    sample_seed : int

    Returns
    -------
    dict
        ``pb_status``, ``pb_bound`` (6: degrees, metres), ``pb_nonlinear`` (6: the largest
        PnP pose error found at region corners), ``pb_time`` (s), ``pb_nodes``,
        ``pb_complete`` (possible = reached), ``pb_pixels`` (possible pixels per keypoint),
        ``pb_counterexample`` (λ or None), ``pb_stride``, ``pb_method``.
    """
    start = time.perf_counter()
    if isinstance(stride, bool) or int(stride) != stride or stride < 1 or stride % 2 == 0:
        raise ValueError(f"stride: expected an odd integer >= 1, got {stride!r}")
    hm = backbone.heatmap_size
    factors = scale_factors(seed.image_size, hm)
    V = np.asarray(seed.keypoints, dtype=np.float64)
    centers = np.clip(np.rint(to_input_pixels(V, factors)), 0, hm - 1).astype(np.int64)
    key = (id(backbone), hashlib.sha1(hull.vertices.numpy().tobytes()).hexdigest())
    key += (centers.tobytes(), int(stride), float(timeout), method)
    before = time.perf_counter() - start
    regions, pixels, search_time = _regions(key, backbone, hull, centers, stride, timeout, method)
    start = time.perf_counter()  # the search is counted once, cached or not
    deviations = [to_image_pixels(p, factors) - v for p, v in zip(pixels, V)]
    bound, extremes = linearised_bound(M, deviations)

    # Nonlinear check: PnP at the extreme and at random combinations of region pixels.
    rng = np.random.default_rng(sample_seed)
    random = np.stack([rng.integers(0, len(d), random_corners) for d in deviations], 1)
    picks = np.concatenate([extremes, random.reshape(-1, len(deviations))])
    V_corner = np.stack([V + np.stack([d[i] for d, i in zip(deviations, row)]) for row in picks])
    nonlinear = _pose_errors(seed, V_corner, R, t).max(0)

    # Witnesses are real images: their argmax pose decides 'violated'.
    points = [torch.zeros(hull.n, dtype=torch.float64)]
    points += [lam for w in regions.witnesses for lam in w.values()]
    lam = torch.unique(torch.stack(points), dim=0)
    with torch.no_grad():
        uv = argmax_keypoints(backbone(hull.image(lam)).float()).double().numpy()
    errors = _pose_errors(seed, to_image_pixels(uv, factors), R, t)
    outside = np.flatnonzero(~np.all(errors <= eps, axis=1))
    if outside.size:
        status, counterexample = "violated", lam[outside[0]].tolist()
    else:
        inside = np.all(kappa * bound <= eps)
        status, counterexample = ("holds" if inside else "unknown"), None
    return {
        "pb_status": status,
        "pb_bound": bound.tolist(),
        "pb_nonlinear": nonlinear.tolist(),
        "pb_time": before + search_time + time.perf_counter() - start,
        "pb_nodes": regions.nodes,
        "pb_complete": regions.complete,
        "pb_pixels": [len(p) for p in pixels],
        "pb_counterexample": counterexample,
        "pb_stride": int(stride),
        "pb_method": method,
    }


_CACHE: dict = {}


def _regions(key, backbone, hull, centers, stride: int, timeout: float, method: str):
    """Possible pixels of each keypoint over ``hull`` and the search's seconds; the last
    few are kept, since the instances of one hull (its α, κ cells) follow each other.
    An entry holds its backbone, so the ``id`` in its key cannot be reused meanwhile."""
    if key not in _CACHE:
        start = time.perf_counter()
        hm = backbone.heatmap_size
        pooling = keypoint_pooling(centers, np.full_like(centers, (stride - 1) // 2), (hm, hm))
        proxy = build_proxy(backbone, pooling, centers).eval()
        sizes = proxy.spec.group_sizes
        regions = reachable_argmax(proxy, hull, sizes, method=method, timeout=timeout)
        pixels = region_pixels(regions, pooling, hm)
        while len(_CACHE) >= 4:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = (backbone, regions, pixels, time.perf_counter() - start)
    return _CACHE[key][1:]


def _pose_errors(seed, V, R, t) -> np.ndarray:
    """Pose errors ``(B, 6)`` of PnP (from the nominal pose) on keypoints ``V (B, K, 2)``."""
    B = len(V)
    R_hat, t_hat = solve_pnp_batch(
        seed.points_3d, V, seed.K, (np.broadcast_to(R, (B, 3, 3)), np.broadcast_to(t, (B, 3)))
    )
    dr = wrap_degrees(euler_from_matrix(R_hat) - euler_from_matrix(R)[None])
    return np.concatenate([dr, np.abs(t_hat - t)], axis=1)
