"""kpstudy.models.evaluation: pose errors from keypoints (infinite where PnP flags the
pose) and the evaluation of both heads of a trained checkpoint."""

from __future__ import annotations

import numpy as np

from kpstudy.models import evaluation as evaluate_module
from kpstudy.models.data import load_keypoint_set
from kpstudy.models.evaluation import evaluate, inside, pose_errors
from kpstudy.pose.pnp import PnPResult
from tests.conftest import views


def test_ground_truth_keypoints_give_the_ground_truth_pose(tiny_dataset):
    data = load_keypoint_set(tiny_dataset, "test", 64)
    errors = pose_errors(data.points_3d, data.image_keypoints, data.K, data.R, data.t)
    assert errors.shape == (2, 6) and errors.max() < 1e-4
    assert inside(errors, 0.5).all()
    assert not inside(np.array([[0, 0, 10.1, 0, 0, 0], [0, 0, 0, 0, 0, 19.9]]), 1.0)[0]
    clustered = 80 + np.random.default_rng(0).normal(0, 1e-4, data.image_keypoints.shape)
    assert np.isinf(pose_errors(data.points_3d, clustered, data.K, data.R, data.t)).all()


def test_a_pose_that_pnp_flags_has_an_infinite_error(P, K, monkeypatch):
    R, t, V = views(3, 25, K, P)

    def flagged_single(P_, V_, K_, init=None, **kw):
        return PnPResult(R[0], t[0], False, 0.0, 1.0)

    monkeypatch.setattr(evaluate_module, "solve_pnp", flagged_single)
    assert np.isinf(pose_errors(P, V, np.stack([K] * 3), R, t)).all()


def test_evaluate_reports_both_heads(checkpoint, tiny_dataset):
    summary, per_image = evaluate(checkpoint, tiny_dataset, "test")
    assert summary["head"].tolist() == ["argmax", "dsnt"]
    for column in ("pck@1", "pck@2", "pck@4", "inside_xi@0.5", "inside_xi@1", "inside_xi@2"):
        assert summary[column].between(0, 1).all()
    assert (summary["pck@1"] <= summary["pck@2"]).all() and (
        summary["pck@2"] <= summary["pck@4"]
    ).all()
    assert len(per_image) == 4 and {"roll", "tz", "inside_xi@1.5"} <= set(per_image)
