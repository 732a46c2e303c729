"""data_gen.keypoints: the canonical 23 keypoints of the airliner."""

import numpy as np

from data_gen.keypoints import AIRLINER_KEYPOINTS, KEYPOINT_NAMES, airliner_keypoints


def test_keypoints_are_23_named_points_of_an_airliner():
    P = airliner_keypoints()
    assert P.shape == (23, 3) and len(set(KEYPOINT_NAMES)) == 23 == len(AIRLINER_KEYPOINTS)
    extent = P.max(0) - P.min(0)
    assert 35 <= extent[0] <= 45  # length
    assert 30 <= extent[1] <= 40  # span
    left = [n for n in KEYPOINT_NAMES if n.startswith("left_")]
    for name in left:  # left and right mirror each other about the fuselage axis
        li, ri = KEYPOINT_NAMES.index(name), KEYPOINT_NAMES.index("right_" + name[5:])
        np.testing.assert_allclose(P[li] * [1, -1, 1], P[ri])
