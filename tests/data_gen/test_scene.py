"""data_gen.scene: keypoint visibility."""

from __future__ import annotations

import numpy as np

from data_gen.keypoints import KEYPOINT_NAMES
from data_gen.render import Frame
from data_gen.scene import keypoint_visibility


def test_a_keypoint_behind_the_camera_is_not_visible():
    """Nothing drawn (depth 0): keypoints in front are inside but hidden; behind the camera,
    whose projection is a mirror image inside the frame, they are outside (0), not 2."""
    h, w = 20, 32
    frame = Frame(
        np.zeros((h, w, 3), np.uint8),
        np.zeros((h, w), np.float32),
        np.zeros((h, w), np.float32),
        np.full((h, w), -1, np.int32),
    )
    K = np.array([[30.0, 0, 16], [0, 30.0, 10], [0, 0, 1]])
    points = np.zeros((len(KEYPOINT_NAMES), 3))
    points[:, 0] = np.linspace(-1, 1, len(points))
    _, front = keypoint_visibility(frame, points, np.eye(3), np.array([0, 0, 50.0]), K)
    _, behind = keypoint_visibility(frame, points, np.eye(3), np.array([0, 0, -50.0]), K)
    assert (front == 1).all() and (behind == 0).all()
