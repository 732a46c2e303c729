"""The allocation method on one instance: seed image → verification instance → record
(paper §5–6, docs/design.md §1).

For a trained backbone, the seed image's ground truth and the vertices of a convex hull
of perturbed images, at one cell ``(α, κ)``:

1. nominal pose: OpenCV PnP on the ground-truth keypoints;
2. sensitivity ``dξ/dv`` at that pose, in heatmap pixels;
3. optimal integer cells: under the sound ``'heatmap'`` reading, pixel ranges
   ``[lo, hi]`` per axis whose every pixel keeps the first-order pose error, measured from
   the *exact* ground-truth keypoints, within ``α ε / κ``
   (:func:`kpstudy.pose.allocation.allocate_cells`); where the pixel grid alone exceeds it
   the instance is ``not_certifiable``. Under ``'paper'``, the paper's tolerances ``δv``
   (``κ |M| δv ≤ α ε``, per image pixel) around the rounded keypoints;
4. pooling on those cells → the proxy network and its spec ("each keypoint's own cell
   wins");
5. :func:`kpstudy.verify.bab.verify` over the exact hull of the preprocessed vertices.

Steps 1–4 are :func:`build_instance`, which returns the proxy, hull and spec without
verifying them (:mod:`kpstudy.study.vnncomp` writes them for other verifiers); step 5 and
the record are :func:`verify_instance`. :mod:`kpstudy.certify.hull` runs both on each
cell of a hull, with the pose-bound method beside them (:func:`kpstudy.certify.hull.certify`).

The record also says how the target model (softmax → DSNT → PnP) does on the seed (its
pose error and whether it lies in Ξ; the verified rate counts only those seeds) and, for
``holds``, how it does on images sampled from the hull: the fraction whose pose error
lies in Ξ. A proof covers the proxy and the linearised pose model; that fraction shows
whether the paper's assumptions (argmax ≈ DSNT, first-order PnP) hold on the instance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from kpstudy import _checks
from kpstudy._memo import digest, remember
from kpstudy.certify.pose_bound_attack import argmax_outside
from kpstudy.models.evaluation import pose_errors
from kpstudy.models.heads import dsnt_keypoints
from kpstudy.models.pooling import keypoint_cells
from kpstudy.models.preprocess import (
    scale_factors,
    to_image_pixels,
    to_input_pixels,
    to_model_input,
)
from kpstudy.models.proxy import KeypointProxy, build_proxy
from kpstudy.pose.allocation import (
    Allocation,
    CellAllocation,
    allocate_cells,
    allocate_tolerances,
    allocation_scale,
    cell_error,
)
from kpstudy.pose.geometry import inside_tolerance, tolerance
from kpstudy.pose.pnp import solve_pnp
from kpstudy.pose.sensitivity import pose_sensitivity
from kpstudy.verify import ConvexHull, verify
from kpstudy.verify.bab import check_verify
from kpstudy.verify.spec import ArgmaxSpec

__all__ = [
    "AllocationOptions",
    "SeedImage",
    "VerificationInstance",
    "build_instance",
    "target_pose_errors",
    "verify_instance",
]


@dataclass(frozen=True)
class AllocationOptions:
    """The allocation method's verification of an instance, :func:`verify_instance`'s
    keywords of the same names and defaults (:func:`kpstudy.verify.bab.verify`'s bound method,
    ``'auto'``: the zonotope; seconds; node budget, ``None``: the seconds alone), checked
    by :func:`kpstudy.verify.bab.verify`'s rules when made: a ``ValueError`` names the first
    that is not valid. The one check of these options outside the verifier
    (:func:`kpstudy.certify.hull.certify_cells`, the study's settings and profiles)."""

    method: str = "auto"
    timeout: float = 60.0
    max_nodes: int | None = None

    def __post_init__(self) -> None:
        check_verify(self.method, self.timeout, self.max_nodes)


@dataclass(frozen=True)
class SeedImage:
    """Ground truth of one seed image.

    Attributes
    ----------
    image_id : int
    keypoints : ndarray, (K, 2)
        Ground-truth ``(u, v)`` in image pixels.
    K : ndarray, (3, 3)
        Intrinsics.
    points_3d : ndarray, (K, 3)
        Keypoints in the object frame, metres.
    image_size : (int, int)
        ``(W, H)`` of the rendered image.
    """

    image_id: int
    keypoints: np.ndarray
    K: np.ndarray
    points_3d: np.ndarray
    image_size: tuple[int, int]

    @classmethod
    def from_keypoint_set(cls, data, index: int) -> SeedImage:
        """Image ``index`` of a :class:`kpstudy.models.data.KeypointSet`."""
        return cls(
            int(data.image_ids[index]),
            data.image_keypoints[index],
            data.K[index],
            data.points_3d,
            tuple(data.image_size),
        )


def target_pose_errors(backbone: nn.Module, images: torch.Tensor, seed: SeedImage, R, t):
    """Pose errors ``(B, 6)`` (degrees, metres) of softmax → DSNT → PnP on ``images``
    ``(B, 3, s, s)`` (normalised model inputs) against the pose ``(R, t)``; ``inf`` where
    PnP rejects the keypoints (:func:`kpstudy.models.evaluation.pose_errors`)."""
    with torch.no_grad():
        uv = dsnt_keypoints(backbone(images).float()).double().numpy()  # heatmap pixels
    image_uv = to_image_pixels(uv, scale_factors(seed.image_size, backbone.heatmap_size))
    B = len(uv)
    return pose_errors(
        seed.points_3d,
        image_uv,
        np.broadcast_to(seed.K, (B, 3, 3)),
        np.broadcast_to(R, (B, 3, 3)),
        np.broadcast_to(t, (B, 3)),
    )


@dataclass(frozen=True)
class VerificationInstance:
    """One seed image's verification instance (steps 1–4 of the module docstring).

    Attributes
    ----------
    proxy : KeypointProxy or None
        Backbone → per-keypoint cell pooling (eval mode), output ``(B, Σ_k cells_k)``;
        None when not ``feasible``.
    hull : ConvexHull
        Over the ``n + 1`` normalised, resized vertices, shape ``(n+1, 3, s, s)``.
    spec : ArgmaxSpec or None
        ``proxy.spec``: each keypoint's target cell wins.
    inputs : Tensor, (n+1, 3, s, s)
        The hull's vertices as model inputs (normalised; row 0 the seed image).
    allocation : CellAllocation or Allocation
        Under ``'heatmap'`` the cells around the exact keypoints
        (:func:`kpstudy.pose.allocation.allocate_cells`); under ``'paper'`` the paper's
        tolerances (:func:`kpstudy.pose.allocation.allocate_tolerances`, ``dv``).
    tolerance_units : str
        How the allocation was computed (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`).
    feasible : bool
        False when the pixel grid alone exceeds the tolerance to first order (``'heatmap'``
        only): the instance is not certifiable at this heatmap resolution.
    cells : tuple of ndarray of int, ((K, 2), (K, 2)) or None
        ``(lo, hi)``: each keypoint's cell, first and last heatmap pixel per axis
        ``(u, v)`` (under ``'paper'`` it may overhang the heatmap).
    first_order : float
        Largest first-order pose error over every pixel of every cell, measured from the
        exact keypoints, as a multiple of ``ε / κ`` (≤ 1 for a feasible ``'heatmap'``
        instance; what the ``'paper'`` reading lets through otherwise).
    centers : ndarray of int, (K, 2)
        Rounded ground-truth keypoints ``(u, v)`` in heatmap pixels (each inside its cell).
    R : ndarray, (3, 3)
    t : ndarray, (3,)
        Nominal pose (PnP on the ground-truth keypoints), object → camera, metres.
    M : ndarray, (6, 2K)
        Sensitivity ``dξ/dv`` at the nominal pose, per heatmap pixel (degrees, metres).
    xi : ndarray, (6,)
        Ξ's half-widths ``α·[10°, 10°, 10°, 4, 4, 20 m]`` (degrees, metres).
    """

    proxy: KeypointProxy | None
    hull: ConvexHull
    spec: ArgmaxSpec | None
    inputs: torch.Tensor
    allocation: CellAllocation | Allocation
    tolerance_units: str
    feasible: bool
    cells: tuple[np.ndarray, np.ndarray] | None
    first_order: float
    centers: np.ndarray
    R: np.ndarray
    t: np.ndarray
    M: np.ndarray
    xi: np.ndarray


def build_instance(
    backbone: nn.Module,
    vertices,
    seed: SeedImage,
    *,
    alpha: float = 1.0,
    kappa: float = 1.0,
    w1: float = 1.0,
    w2: float = 5.0,
    tolerance_units: str = "heatmap",
) -> VerificationInstance:
    """The proxy, hull and spec that :func:`verify_instance` verifies (no verification).

    Parameters
    ----------
    backbone : nn.Module
        Trained heatmap backbone (eval mode) with ``input_size`` and ``heatmap_size``.
    vertices : ndarray, (n+1, H, W, 3)
        The seed image first, then the perturbed images, values in [0, 255], at the
        render's resolution or already at the model input (they are resized by F0).
    seed : SeedImage
        The seed image's ground truth.
    alpha, kappa, w1, w2 : float
        Tolerance scale (``ε = α·[10°, 10°, 10°, 4, 4, 20 m]``), sensitivity margin κ and
        allocation weights.
    tolerance_units : {'heatmap', 'paper'}
        How the cells are chosen (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`):
        ``'heatmap'`` (sound to first order), pixel ranges around the exact keypoints;
        ``'paper'``, the paper's half-widths, allocated per image pixel, around the rounded
        keypoints.

    Returns
    -------
    VerificationInstance

    Raises
    ------
    ValueError
        Naming ``alpha``, ``kappa``, ``tolerance_units``, ``backbone``, ``vertices`` or
        ``seed`` (no valid nominal pose, or a keypoint outside the heatmap).
    """
    alpha = float(_checks.positive(alpha, "alpha"))
    kappa = float(_checks.positive(kappa, "kappa"))
    allocation_scale(tolerance_units, None)  # checks the name
    for name in ("input_size", "heatmap_size"):
        if not hasattr(backbone, name):
            raise ValueError(f"backbone: expected a kpstudy backbone with .{name}")
    vertices = np.asarray(vertices)
    if vertices.ndim != 4 or vertices.shape[-1] != 3 or len(vertices) < 2:
        raise ValueError(
            f"vertices: expected (n+1, H, W, 3) images with n >= 1, got shape {vertices.shape}"
        )
    s, hm = backbone.input_size, backbone.heatmap_size
    P, V, K = seed.points_3d, np.asarray(seed.keypoints, float), np.asarray(seed.K, float)
    xi = tolerance(alpha)
    eps_r, eps_t = xi[:3], xi[3:]

    nominal = solve_pnp(P, V, K)
    if not nominal.valid:
        raise ValueError(
            "seed: PnP on the ground-truth keypoints gives no valid pose (smallest depth "
            f"{nominal.min_depth:.4g} m, residual {nominal.rms_px:.3g} px)"
        )
    R, t = nominal
    factors = scale_factors(seed.image_size, hm)
    M = cached_sensitivity(P, V, K, R, t, factors)
    exact = to_input_pixels(V, factors)
    centers = np.rint(exact).astype(np.int64)
    if np.any((centers < 0) | (centers >= hm)):
        k = int(np.flatnonzero(np.any((centers < 0) | (centers >= hm), axis=1))[0])
        raise ValueError(
            f"seed: keypoint {k} lies outside the {hm}×{hm} heatmap at {centers[k].tolist()} "
            "(only seeds with every keypoint in the image can be certified)"
        )
    offsets = exact - centers
    if tolerance_units == "heatmap":
        allocation = _cells(M, offsets, eps_r, eps_t, kappa, w1, w2, centers, hm - 1 - centers)
        below, above, feasible = allocation.below, allocation.above, allocation.feasible
    else:
        M_image = cached_sensitivity(P, V, K, R, t, None)
        allocation = _allocation(M_image, eps_r, eps_t, kappa, w1, w2, hm)
        below = above = allocation.dv
        feasible = True
    first_order = float(np.max(kappa * cell_error(M, offsets, below, above) / xi))
    cells = (centers - below, centers + above) if feasible else None
    proxy = None
    if feasible:
        proxy = build_proxy(backbone, keypoint_cells(*cells, (hm, hm)), centers).eval()
    x = to_model_input(vertices, size=s)
    return VerificationInstance(
        proxy=proxy,
        hull=ConvexHull(x),
        spec=None if proxy is None else proxy.spec,
        inputs=x,
        allocation=allocation,
        tolerance_units=tolerance_units,
        feasible=feasible,
        cells=cells,
        first_order=first_order,
        centers=centers,
        R=R,
        t=t,
        M=M,
        xi=xi,
    )


_SENSITIVITIES: dict = {}
_ALLOCATIONS: dict = {}


def cached_sensitivity(P, V, K, R, t, scale) -> np.ndarray:
    """:func:`kpstudy.pose.sensitivity.pose_sensitivity` (its first call in a process takes
    about 2 s), kept by the content of its inputs: a campaign's instances of one seed
    image share it."""
    key = digest(P, V, K, R, t, () if scale is None else scale)
    make = lambda: pose_sensitivity(P, V, K, R, t, scale=scale)  # noqa: E731
    return remember(_SENSITIVITIES, key, make, 16).copy()


def _cells(M, offsets, eps_r, eps_t, kappa, w1, w2, max_below, max_above) -> CellAllocation:
    """:func:`kpstudy.pose.allocation.allocate_cells`, kept by the content of its inputs."""
    key = digest(M, offsets, eps_r, eps_t, max_below, max_above, [kappa, w1, w2])
    make = lambda: allocate_cells(  # noqa: E731
        M, offsets, eps_r, eps_t, kappa, w1, w2, max_below=max_below, max_above=max_above
    )
    return remember(_ALLOCATIONS, key, make, 64)


def _allocation(M, eps_r, eps_t, kappa, w1, w2, max_dv) -> Allocation:
    """:func:`kpstudy.pose.allocation.allocate_tolerances`, kept by the content of its inputs:
    a campaign's hulls of one seed image share its allocation per (α, κ)."""
    key = digest(M, eps_r, eps_t, [kappa, w1, w2, max_dv])
    make = lambda: allocate_tolerances(M, eps_r, eps_t, kappa, w1, w2, max_dv=max_dv)  # noqa: E731
    return remember(_ALLOCATIONS, key, make, 64)


def verify_instance(
    backbone: nn.Module,
    instance: VerificationInstance,
    seed: SeedImage,
    *,
    method: str = "auto",
    timeout: float = 60.0,
    max_nodes: int | None = None,
    check_samples: int = 200,
    sample_seed: int = 0,
) -> dict:
    """The allocation method's record of one instance: :func:`kpstudy.verify.bab.verify` on
    ``instance`` (:func:`build_instance`'s, for ``backbone`` and ``seed``) and the target
    model's pose errors.

    The keywords are :func:`kpstudy.certify.hull.certify_cells`'s; the record is its record
    without ``tolerance_units``, the ``pb_*`` entries and ``total_time``. An instance
    that is not ``feasible`` is ``not_certifiable`` and is not verified.
    """
    hull, allocation, xi, R, t = (
        instance.hull,
        instance.allocation,
        instance.xi,
        instance.R,
        instance.t,
    )
    seed_error = target_pose_errors(backbone, instance.inputs[:1], seed, R, t)[0]
    record = {
        "image_id": seed.image_id,
        "n": hull.n,
        "status": "not_certifiable",
        "time": 0.0,
        "nodes": 0,
        "stopped": None,
        "group_status": [],
        "margin_bracket": [None, None],
        "cells": None,
        "dv": None,
        "delta": allocation.delta,
        "objective": allocation.objective,
        "first_order": instance.first_order,
        "seed_error": seed_error.tolist(),
        "seed_inside": bool(inside_tolerance(seed_error, xi)),
        "counterexample": None,
        "empirical_inside": None,
        "argmax_outside": None,
        "empirical_samples": 0,
    }
    if not instance.feasible:
        return record
    result = verify(
        instance.proxy, hull, instance.spec, method=method, timeout=timeout, max_nodes=max_nodes
    )
    lo, hi = instance.cells
    record.update(
        status=result.status,
        time=result.time,
        nodes=result.nodes,
        stopped=result.stats.get("stopped"),
        group_status=list(result.group_status),
        margin_bracket=list(result.margin_bracket()),
        cells=[lo.tolist(), hi.tolist()],
        dv=((hi - lo) / 2.0).tolist(),
        counterexample=(
            None if result.counterexample is None else result.counterexample.point.tolist()
        ),
    )
    if result.status == "holds" and check_samples:
        images = hull.image(hull.sample(int(check_samples), sample_seed))
        errors = target_pose_errors(backbone, images, seed, R, t)
        record["empirical_inside"] = float(np.mean(inside_tolerance(errors, xi)))
        outside = argmax_outside(backbone, images, seed, R, t, xi)
        record["argmax_outside"] = len(outside) / int(check_samples)
        record["empirical_samples"] = int(check_samples)
    return record
