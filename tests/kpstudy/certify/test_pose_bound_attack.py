"""kpstudy.certify.pose_bound_attack: the targeted witness."""

import numpy as np
import pytest
import torch

from kpstudy.certify import pose_bound_attack as attack
from kpstudy.models.heads import argmax_keypoints
from tests.helpers.pose_bound import Ramp, unit_hull


def test_the_targeted_witness_reaches_joint_combinations_and_only_those():
    peaks = np.array([[10, 10], [20, 20], [30, 30]])
    moved = peaks + [1, 0]
    # Keypoint k moves once b·gain_k > 1 − b: at b > 1/(1 + gain_k) = 0.75, 0.5, 0.25.
    model = Ramp(peaks, moved, [1 / 3, 1.0, 3.0])
    hull = unit_hull()
    seed = [torch.zeros(1, dtype=torch.float64)]
    lam = attack.targeted_witness(model, hull, moved, seed)
    assert lam is not None and lam.item() > 0.75
    heat = model(hull.image(lam[None], dtype=torch.float32))
    assert np.array_equal(argmax_keypoints(heat)[0].numpy(), moved)
    # Keypoint 0 at its peak (b < 0.75) with keypoint 1 moved (b > 0.5): reachable.
    both = np.stack([peaks[0], moved[1], moved[2]])
    assert 0.5 < attack.targeted_witness(model, hull, both, seed).item() < 0.75
    # Keypoint 1 at its peak (b < 0.5) with keypoint 0 moved (b > 0.75): no image does it.
    assert (
        attack.targeted_witness(model, hull, np.stack([moved[0], peaks[1], moved[2]]), seed) is None
    )


def test_a_free_keypoint_and_alternative_targets():
    peaks = np.array([[10, 10], [20, 20], [30, 30]])
    moved = peaks + [1, 0]
    model = Ramp(peaks, moved, [1 / 3, 1.0, 3.0])
    hull, seed = unit_hull(), [torch.zeros(1, dtype=torch.float64)]
    # Keypoint 0 moved with keypoint 1 at its peak is no image's argmax; keypoint 0 moved
    # with keypoint 1 free is (b > 0.75).
    unreachable = np.stack([moved[0], peaks[1], moved[2]])
    assert attack.targeted_witness(model, hull, unreachable, seed) is None
    free = unreachable.copy()
    free[1:] = -1
    assert attack.targeted_witness(model, hull, free, seed).item() > 0.75
    # Several targets at once: the first reached is returned.
    lam = attack.targeted_witness(model, hull, np.stack([unreachable, free]), seed)
    assert lam is not None and lam.item() > 0.75
    with pytest.raises(ValueError, match="targets: expected shape"):
        attack.targeted_witness(model, hull, np.zeros(2, dtype=np.int64), seed)
