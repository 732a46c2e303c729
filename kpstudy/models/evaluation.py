"""Evaluating a trained backbone: keypoint accuracy and the pose it gives through PnP.

For each held-out image, both target heads (softmax → argmax, softmax → DSNT) give 23
keypoints in heatmap pixels. Reported per head: PCK at 1, 2 and 4 heatmap pixels and the
mean keypoint error (keypoints inside the image), then the pose from OpenCV's PnP on all
keypoints mapped back to image pixels, its error against the ground-truth pose per axis
(docs/design.md §3), and the fraction of images whose pose error lies inside
``Ξ = {|δξ| ≤ α ε}`` for each α.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from kpstudy.models.data import load_keypoint_set
from kpstudy.models.training import load_checkpoint, pck, predict
from kpstudy.pose.geometry import POSE_AXES, inside_tolerance, pose_error, tolerance
from kpstudy.pose.pnp import solve_pnp

ALPHAS = (0.5, 1.0, 1.5, 2.0)


def pose_errors(points_3d, image_keypoints, K, R, t) -> np.ndarray:
    """Per-image pose error ``(N, 6)`` (degrees, metres) of PnP on ``image_keypoints``
    ``(N, K, 2)`` (image pixels) against the ground truth ``R (N, 3, 3)``, ``t (N, 3)``.
    Keypoints PnP cannot use (collinear, clustered, non-finite) and poses it flags as not
    valid (a point behind the camera, a residual near the keypoints' spread: see
    :class:`kpstudy.pose.pnp.PnPResult`) give an infinite error, so they never lie inside Ξ."""
    out = np.full((len(image_keypoints), 6), np.inf)
    for i, uv in enumerate(image_keypoints):
        try:
            pose = solve_pnp(points_3d, uv, K[i])
        except ValueError:
            continue
        if pose.valid:
            out[i] = np.concatenate(pose_error(pose.R, pose.t, R[i], t[i]))
    return out


def inside(errors: np.ndarray, alpha: float) -> np.ndarray:
    """Which rows of ``errors (N, 6)`` lie inside Ξ scaled by ``alpha``."""
    return inside_tolerance(errors, tolerance(alpha))


def evaluate(checkpoint, data_dir, split: str = "test", alphas=ALPHAS, *, limit=None):
    """Keypoint and pose metrics of the checkpoint's backbone on one split.

    Returns
    -------
    summary : DataFrame
        One row per head (``argmax``, ``dsnt``): ``pck@1``, ``pck@2``, ``pck@4``,
        ``mean_error`` (heatmap pixels), median pose error per axis (``median_roll`` …),
        ``inside_xi@α`` for each α, ``images``.
    per_image : DataFrame
        ``image_id``, ``head``, the six pose errors (``inf`` where PnP gives no valid
        pose), ``pnp_valid`` and ``inside_xi@α``.

    Raises
    ------
    ValueError
        The checkpoint's backbone predicts non-finite keypoints.
    """
    backbone, state = load_checkpoint(checkpoint)
    data = load_keypoint_set(data_dir, split, backbone.input_size, limit=limit)
    if data.keypoint_names != state["keypoint_names"]:
        raise ValueError(f"data: the keypoints of {data_dir} are not the checkpoint's")
    heads = dict(zip(("argmax", "dsnt"), predict(backbone, data.images)))
    for head, uv in heads.items():
        if not np.isfinite(uv).all():
            image = int(data.image_ids[np.flatnonzero(~np.isfinite(uv).all((1, 2)))[0]])
            raise ValueError(
                f"checkpoint: {checkpoint} predicts non-finite {head} keypoints "
                f"(image id {image}); retrain it"
            )
    summary, per_image = [], []
    for head, uv in heads.items():
        errors = pose_errors(data.points_3d, data.to_image_pixels(uv), data.K, data.R, data.t)
        frame = pd.DataFrame(errors, columns=list(POSE_AXES))
        frame.insert(0, "head", head)
        frame.insert(0, "image_id", data.image_ids)
        frame["pnp_valid"] = np.isfinite(errors).all(1)
        row = dict(head=head, **pck(uv, data.keypoints, data.visibility > 0))
        row.update({f"median_{a}": float(np.median(errors[:, j])) for j, a in enumerate(POSE_AXES)})
        for alpha in alphas:
            frame[f"inside_xi@{alpha:g}"] = inside(errors, alpha)
            row[f"inside_xi@{alpha:g}"] = float(frame[f"inside_xi@{alpha:g}"].mean())
        row["images"] = len(data)
        summary.append(row)
        per_image.append(frame)
    return pd.DataFrame(summary), pd.concat(per_image, ignore_index=True)
