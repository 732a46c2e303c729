"""kpstudy.models.heads: the DSNT and argmax heads and the target model."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpstudy.models import TargetModel, argmax_keypoints, build_backbone, dsnt_keypoints
from tests.helpers.heatmaps import gaussian_heatmaps


def test_dsnt_and_argmax_agree_on_symmetric_heatmaps():
    """Paper Proposition 1: symmetric marginals → the softmax's mean is its mode."""
    centers = [(20, 30), (33, 17), (45, 44)]
    for sigma in (0.7, 1.5, 3.0):
        logits = gaussian_heatmaps(centers, (64, 64), sigma, log=True)
        np.testing.assert_allclose(dsnt_keypoints(logits)[0].numpy(), centers, atol=1e-6)
        assert argmax_keypoints(logits)[0].tolist() == [list(c) for c in centers]


def test_dsnt_and_argmax_disagree_on_a_skewed_heatmap():
    """A peak at (20, 30) with a long tail to the right: the argmax stays on the peak,
    the mean moves right by more than a pixel."""
    logits = gaussian_heatmaps([(20, 30)], (64, 64), 1.0, log=True)
    u = torch.arange(64).double()
    tail = torch.where(u > 20, -0.5 - 0.08 * (u - 20), torch.tensor(-1e9).double())
    logits = torch.maximum(
        logits, tail.expand(64, 64) - 0.5 * (torch.arange(64)[:, None] - 30) ** 2
    )
    assert argmax_keypoints(logits)[0, 0].tolist() == [20, 30]
    mean = dsnt_keypoints(logits)[0, 0]
    assert mean[0] > 21.5 and abs(mean[1] - 30) < 1e-6


def test_target_model_heads():
    net = build_backbone("cnn", 3).eval()
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        h = net(x)
        torch.testing.assert_close(TargetModel(net, "dsnt")(x), dsnt_keypoints(h))
        assert torch.equal(TargetModel(net, "argmax")(x), argmax_keypoints(h))
    with pytest.raises(ValueError, match="head: expected one of"):
        TargetModel(net, "mean")
