"""One seed image's hull of perturbed images → one record per (α, κ) cell: both methods.

:func:`certify_cells` drives one hull through the study's grid of cells ``(α, κ)``: for
each cell, the allocation method on its instance
(:func:`~kpstudy.certify.allocation_method.build_instance`, then
:func:`~kpstudy.certify.allocation_method.verify_instance`) and, optionally, the
pose-bound method on the same hull (one
:class:`~kpstudy.certify.pose_bound_method.HullPoseBound`, made with the first cell and
decided per cell, so that what depends on the hull alone is made once), in one record.
:func:`certify` is one cell: one instance, one record (docs/design.md §4.12).

Units: α scales Ξ's half-widths ``α·[10°, 10°, 10°, 4, 4, 20 m]``, κ ≥ 1 is the
linearisation's safety margin; times in seconds.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace

import numpy as np
from torch import nn

from kpstudy import _checks
from kpstudy.certify.allocation_method import (
    AllocationOptions,
    SeedImage,
    build_instance,
    cached_sensitivity,
    verify_instance,
)
from kpstudy.certify.pose_bound_method import HullPoseBound, PoseBoundOptions

__all__ = ["POSE_BOUND_KEYWORDS", "certify", "certify_cells", "pose_bound_options"]

#: :func:`certify_cells`' keyword of the pose-bound method (and the
#: :class:`kpstudy.study.campaign.Settings` field of that name) → its
#: :class:`~kpstudy.certify.pose_bound_method.PoseBoundOptions` field.
POSE_BOUND_KEYWORDS = {
    "pose_bound_method": "method",
    "pose_bound_timeout": "timeout",
    "pose_bound_nodes": "max_nodes",
    "pose_bound_start_depth": "start_depth",
    "pose_bound_start_splits": "start_splits",
    "pose_bound_refine_nodes": "refine_nodes",
    "pose_bound_stride": "stride",
}


def pose_bound_options(prefix: str = "", **chosen) -> PoseBoundOptions | None:
    """The pose-bound method's options of :data:`POSE_BOUND_KEYWORDS` ``chosen`` (one left
    out: its default), checked: a ``ValueError`` names the keyword (or the unknown ones),
    after ``prefix``. ``None`` when ``pose_bound_timeout`` is ``None`` or left out: the
    method is skipped, and the other keywords are checked all the same."""
    unknown = sorted(set(chosen) - set(POSE_BOUND_KEYWORDS))
    if unknown:
        raise ValueError(
            f"{prefix}unknown settings {unknown}; expected {sorted(POSE_BOUND_KEYWORDS)}"
        )
    options = {POSE_BOUND_KEYWORDS[name]: value for name, value in chosen.items()}
    timeout = options.pop("timeout", None)
    with _checks.named({v: k for k, v in POSE_BOUND_KEYWORDS.items()}, prefix):
        _checks.seconds(timeout, "timeout", optional=True)
        checked = PoseBoundOptions(**options)
        return None if timeout is None else replace(checked, timeout=timeout)


def certify(backbone: nn.Module, vertices, seed: SeedImage, *, alpha=1.0, kappa=1.0, **options):
    """Verify that every image of the hull of ``vertices`` keeps each keypoint in its cell:
    one instance, :func:`certify_cells` with the one cell ``(alpha, kappa)`` and its
    other keywords ``options``; its record."""
    return certify_cells(backbone, vertices, seed, [(alpha, kappa)], **options)[0]


def certify_cells(
    backbone: nn.Module,
    vertices,
    seed: SeedImage,
    cells,
    *,
    w1: float = 1.0,
    w2: float = 5.0,
    method: str = "auto",
    timeout: float = 60.0,
    max_nodes: int | None = None,
    check_samples: int = 200,
    sample_seed: int = 0,
    pose_bound_timeout: float | None = None,
    pose_bound_stride: int = 1,
    pose_bound_method: str = "forward",
    pose_bound_nodes: int | None = None,
    pose_bound_start_depth: int = 0,
    pose_bound_start_splits: float = 0.0,
    pose_bound_refine_nodes: int = 0,
    tolerance_units: str = "heatmap",
) -> list[dict]:
    """Verify that every image of the hull of ``vertices`` keeps each keypoint in its cell,
    for each cell ``(α, κ)`` of the study's grid on this hull.

    The cells share the hull, so what depends on the hull alone is made once: the
    pose-bound method's region search, enumeration and attacks (a
    :class:`kpstudy.certify.pose_bound_method.HullPoseBound`). Both methods' keywords are
    checked before any work (:class:`~kpstudy.certify.allocation_method.AllocationOptions`,
    :func:`pose_bound_options`: the ``pose_bound_*`` ones even when the method is skipped).

    Parameters
    ----------
    backbone, vertices, seed, w1, w2, tolerance_units :
        The instances, as :func:`~kpstudy.certify.allocation_method.build_instance`
        takes them.
    cells : sequence of (float, float)
        ``(alpha, kappa)`` of each instance
        (:func:`~kpstudy.certify.allocation_method.build_instance`'s).
    method, timeout, max_nodes :
        Passed to :func:`kpstudy.verify.bab.verify` (seconds; a node budget, ``None``: the
        seconds alone).
    check_samples : int
        For ``holds``: hull images (Dirichlet) run through the target model; 0 skips.
    sample_seed : int
    pose_bound_timeout : float, optional
        Seconds for the second method,
        :class:`kpstudy.certify.pose_bound_method.HullPoseBound` (reachable keypoint regions
        → certified pose-error bound) on the same hull; ``None`` skips it.
    pose_bound_stride : int
        Its cell side in heatmap pixels (1: the argmax pixel itself).
    pose_bound_method : str
        Its bound method (``'forward'`` or ``'zonotope'``).
    pose_bound_nodes, pose_bound_start_depth, pose_bound_start_splits :
        Its node budget (``None``: the seconds alone; 0: the witnesses alone) and the
        hull's splits before the first bounds
        (:class:`kpstudy.certify.pose_bound_method.HullPoseBound`'s ``max_nodes``,
        ``start_depth``, ``start_splits``).
    pose_bound_refine_nodes : int
        Its focused second searches for an ``unknown`` verdict
        (:class:`~kpstudy.certify.pose_bound_method.HullPoseBound`'s ``refine_nodes``).

    Returns
    -------
    list of dict
        One record per cell, in order: ``image_id``, ``n`` (perturbed vertices),
        ``status`` (``holds`` / ``violated`` / ``unknown``, or ``not_certifiable``: under
        ``'heatmap'`` the pixel grid alone exceeds the tolerance to first order, so nothing
        is verified), ``time`` (verification, s), ``total_time`` (s), ``nodes``, ``stopped``
        (what ended the search early: ``'nodes'`` (``max_nodes`` spent), ``'time'``
        (``timeout`` fired: the verdict depends on the machine), ``'stop'`` (a
        counterexample) or None),
        ``group_status`` (per keypoint), ``margin_bracket`` (the worst keypoint's margin
        over the hull: [root lower bound, smallest found by the attacks], see
        :meth:`kpstudy.verify.result.Result.margin_bracket`), ``cells`` (``[lo, hi]``, each K ×
        [u, v], heatmap px), ``dv`` (K × [δu, δv], the cells' half-widths, heatmap px),
        ``delta``, ``objective``, ``first_order`` (the cells' largest first-order pose error
        from the exact keypoints, a multiple of ``ε / κ``), ``seed_error`` (6 pose errors
        of the target model on the seed, degrees and metres), ``seed_inside`` (that error
        lies in Ξ),
        ``counterexample`` (λ or None), ``empirical_inside`` (fraction of sampled hull
        images whose target pose error lies in Ξ; None unless ``holds``),
        ``argmax_outside`` (fraction of the same images whose argmax → PnP pose leaves
        Ξ: what a ``holds`` under the ``'paper'`` reading lets through; None unless
        ``holds``), ``empirical_samples``, ``tolerance_units``; with
        ``pose_bound_timeout``, the ``pb_*`` entries of
        :meth:`kpstudy.certify.pose_bound_method.HullPoseBound.decide`.
    """
    AllocationOptions(method, timeout, max_nodes)
    _checks.integer(check_samples, "check_samples", minimum=0)
    pose_bound = pose_bound_options(
        pose_bound_method=pose_bound_method,
        pose_bound_timeout=pose_bound_timeout,
        pose_bound_nodes=pose_bound_nodes,
        pose_bound_start_depth=pose_bound_start_depth,
        pose_bound_start_splits=pose_bound_start_splits,
        pose_bound_refine_nodes=pose_bound_refine_nodes,
        pose_bound_stride=pose_bound_stride,
    )
    cells = list(cells)
    if not cells or any(np.shape(c) != (2,) for c in cells):
        raise ValueError(f"cells: expected one or more (alpha, kappa) pairs, got {cells!r}")
    cells = [
        (float(_checks.positive(a, "alpha")), float(_checks.positive(k, "kappa"))) for a, k in cells
    ]
    shared = None  # the pose-bound method on this hull, made with the first cell
    records = []
    for alpha, kappa in cells:
        start = time.perf_counter()
        instance = build_instance(
            backbone,
            vertices,
            seed,
            alpha=alpha,
            kappa=kappa,
            w1=w1,
            w2=w2,
            tolerance_units=tolerance_units,
        )
        record = verify_instance(
            backbone,
            instance,
            seed,
            method=method,
            timeout=timeout,
            max_nodes=max_nodes,
            check_samples=check_samples,
            sample_seed=sample_seed,
        )
        record["tolerance_units"] = tolerance_units
        if pose_bound is not None:
            if shared is None:
                options = dict(asdict(pose_bound), sample_seed=sample_seed)
                shared = _hull_pose_bound(backbone, instance, seed, options)
            record.update(shared.decide(instance.xi, kappa))
        record["total_time"] = time.perf_counter() - start
        records.append(record)
    return records


def _hull_pose_bound(backbone, instance, seed: SeedImage, options: dict) -> HullPoseBound:
    """The pose-bound method on ``instance``'s hull, from its nominal pose and the
    sensitivity there per image pixel, with :class:`HullPoseBound`'s keywords
    ``options``."""
    P, V = seed.points_3d, np.asarray(seed.keypoints, float)
    M_image = cached_sensitivity(P, V, np.asarray(seed.K, float), instance.R, instance.t, None)
    return HullPoseBound(backbone, instance.hull, seed, instance.R, instance.t, M_image, **options)
