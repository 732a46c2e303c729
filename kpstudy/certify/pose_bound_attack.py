"""Images of a hull whose argmax → PnP pose leaves Ξ: the pose-bound method's attack.

* ``argmax_pose_errors()`` and :func:`argmax_outside`: the argmax → PnP pipeline's pose
  error at given images (PnP from the nominal pose,
  ``kpstudy.certify.pose_bound_rules.pnp_pose_errors()``);
* ``HullArgmaxPoses``: the same at points λ of one hull, each point's made once, and
  the first point outside Ξ that the float64 model at the exact hull point confirms
  (a *witness*: a real counterexample);
* :func:`targeted_witness`: projected gradient steps (Adam on the vertex weights' logits)
  towards an image whose argmax puts the keypoints on target pixels (docs/design.md
  §4.11).

Shapes and units: images ``(B, 3, s, s)`` are normalised model inputs; λ ``(n,)`` or
``(P, n)`` float64 weights of a hull's perturbed vertices; argmax pixels are heatmap
``(u, v)`` or flat heatmap indices ``v · W + u``; pose errors ``(B, 6)`` are degrees
(wrapped) then metres, ``inf`` where PnP flags the pose; Ξ's half-widths ``eps`` (6,)
in the same units.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from kpstudy._memo import digest
from kpstudy.certify.pose_bound_rules import pnp_pose_errors
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.preprocess import scale_factors, to_image_pixels
from kpstudy.pose.geometry import inside_tolerance

__all__ = ["argmax_outside", "targeted_witness"]


def argmax_outside(backbone, images, seed, R, t, eps) -> np.ndarray:
    """Indices of ``images (B, 3, s, s)`` (normalised model inputs) whose argmax → PnP
    pose lies outside Ξ (half-widths ``eps``, 6: degrees, metres) around ``(R, t)``."""
    errors = argmax_pose_errors(backbone, images, seed, R, t)
    return np.flatnonzero(~inside_tolerance(errors, eps))


def argmax_pose_errors(backbone, images, seed, R, t) -> np.ndarray:
    """Pose errors ``(B, 6)`` (degrees, metres; ``inf`` where PnP flags the pose) of the
    argmax → PnP pipeline on ``images (B, 3, s, s)`` against ``(R, t)``."""
    return argmax_pixels_and_errors(backbone, images, seed, R, t)[1]


def argmax_pixels_and_errors(backbone, images, seed, R, t) -> tuple[np.ndarray, np.ndarray]:
    """The argmax pixels of ``images``, as flat heatmap indices ``(B, K)`` (the first
    maximum, as :func:`argmax_keypoints` takes it), and ``argmax_pose_errors()``."""
    factors = scale_factors(seed.image_size, backbone.heatmap_size)
    with torch.no_grad():
        heatmaps = backbone(images)
    uv = argmax_keypoints(heatmaps)  # (B, K, 2) as (u, v)
    flat = (uv[..., 1] * heatmaps.shape[-1] + uv[..., 0]).numpy()
    errors = pnp_pose_errors(seed, to_image_pixels(uv.double().numpy(), factors), R, t)
    return flat, errors


class HullArgmaxPoses:
    """The argmax → PnP pose of points of one hull, each point's made once.

    Parameters
    ----------
    backbone : nn.Module
        Heatmap backbone with ``heatmap_size``.
    hull : kpstudy.verify.ConvexHull
    seed : kpstudy.certify.allocation_method.SeedImage
    R, t : ndarray, shapes (3, 3) and (3,)
        Nominal pose: every PnP starts there and its error is measured from it.
    """

    def __init__(self, backbone, hull, seed, R, t) -> None:
        self.backbone, self.hull, self.seed, self.R, self.t = backbone, hull, seed, R, t
        self._errors: dict = {}  # λ digest → argmax pose errors (6,)
        self._argmax: dict = {}  # λ digest → argmax pixels, flat heatmap indices (K,)
        self._model64 = None

    def errors(self, lam) -> np.ndarray:
        """``argmax_pose_errors()`` ``(P, 6)`` of ``hull.image(lam)`` for ``lam (P, n)``,
        each point's made once; its argmax pixels are kept for :meth:`pixels`."""
        keys = [digest(row) for row in lam]
        missing = [i for i, k in enumerate(keys) if k not in self._errors]
        if missing:
            images = self.hull.image(lam[missing])
            flat, errors = argmax_pixels_and_errors(
                self.backbone, images, self.seed, self.R, self.t
            )
            for i, f, e in zip(missing, flat, errors):
                self._errors[keys[i]], self._argmax[keys[i]] = e, f
        return np.stack([self._errors[k] for k in keys])

    def pixels(self, lam) -> np.ndarray:
        """The argmax pixels (flat heatmap indices ``(K,)``) of the point ``lam (n,)``,
        which :meth:`errors` evaluated."""
        return self._argmax[digest(lam)]

    def first_outside(self, eps, points) -> list | None:
        """λ (a list) of the first of ``points`` whose image's argmax → PnP pose lies
        outside Ξ (half-widths ``eps``), else None. A point found in the model's dtype
        counts only if the float64 model at the exact hull point
        (``hull.image(λ, float64)``) agrees; None for no ``points``."""
        if not len(points):
            return None
        lam = torch.unique(torch.stack(list(points)), dim=0)
        outside = np.flatnonzero(~inside_tolerance(self.errors(lam), eps))
        if not outside.size:
            return None
        backbone = self.backbone
        if next(backbone.parameters(), torch.empty(0)).dtype == torch.float64:
            return lam[outside[0]].tolist()
        if self._model64 is None:
            self._model64 = copy.deepcopy(backbone).double()
        for rows in np.array_split(outside, -(-len(outside) // 4)):  # the first confirmed
            images = self.hull.image(lam[rows], dtype=torch.float64)
            confirmed = argmax_outside(self._model64, images, self.seed, self.R, self.t, eps)
            if confirmed.size:
                return lam[rows[confirmed[0]]].tolist()
        return None


def targeted_witness(
    backbone, hull, targets, starts, *, steps: int = 100, lr: float = 0.1
) -> torch.Tensor | None:
    """A point λ of ``hull`` whose image puts keypoints' argmax on target pixels, if
    projected gradient steps find one (an attack: None proves nothing).

    Parameters
    ----------
    backbone : nn.Module
        Heatmap model, ``(B, 3, s, s) → (B, K, H, W)``.
    hull : kpstudy.verify.ConvexHull
    targets : array_like of int, shape (K, 2) or (T, K, 2)
        ``(u, v)`` heatmap pixel per keypoint, for one target or T alternatives (all
        searched together); a negative entry leaves that keypoint free.
    starts : list of Tensor, shape (n,)
        λ to start from (one run per start and target, batched).
    steps, lr : int, float
        Adam steps on the vertex weights' logits (a softmax keeps λ in the hull).

    Returns
    -------
    Tensor, shape (n,), float64, or None
        λ whose image's argmax (torch's first maximum) is one target's pixels, on every
        keypoint that target sets, in float32.
    """
    W = backbone.heatmap_size
    targets = torch.as_tensor(np.asarray(targets), dtype=torch.int64)
    targets = targets[None] if targets.ndim == 2 else targets  # (T, K, 2)
    if targets.ndim != 3 or targets.shape[-1] != 2 or not len(targets):
        raise ValueError(f"targets: expected shape (K, 2) or (T, K, 2), got {tuple(targets.shape)}")
    T, S = len(targets), len(starts)
    fixed = (targets >= 0).all(-1).repeat_interleave(S, 0)  # (T·S, K): the set keypoints
    flat = (targets[..., 1] * W + targets[..., 0]).clamp_min(0)
    flat = flat.repeat_interleave(S, 0)[..., None]  # (T·S, K, 1)
    lam0 = torch.stack([torch.as_tensor(s, dtype=torch.float64) for s in starts])
    weights = torch.cat([1.0 - lam0.sum(1, keepdim=True), lam0], 1).clamp_min(1e-3)
    logits = weights.log().float().repeat(T, 1).requires_grad_(True)  # (T·S, n + 1)
    optimiser = torch.optim.Adam([logits], lr=lr)
    for _ in range(steps + 1):
        with torch.enable_grad():
            lam = torch.softmax(logits, 1)[:, 1:]
            heat = backbone(hull.image(lam, dtype=torch.float32)).flatten(2)  # (B, K, H·W)
            target = heat.gather(2, flat)[..., 0]
            rival = heat.scatter(2, flat, float("-inf")).amax(2)
            # < 0: the target is the unique maximum; free keypoints count as reached.
            gap = torch.where(fixed, rival - target, torch.full_like(target, -1.0))
            done = (gap < 0).all(1)
            if done.any():
                return lam[int(done.nonzero()[0])].detach().double()
            if not gap.requires_grad:  # a model without a gradient in its input
                return None
            # The gradient of λ's logits only (the model's parameters get none).
            (logits.grad,) = torch.autograd.grad(torch.relu(gap + 1e-2).sum(), logits)
        optimiser.step()
    return None
