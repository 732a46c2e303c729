"""data_gen.camera: overhead poses and intrinsics."""

import numpy as np
import pytest

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.pose.geometry import euler_from_matrix, project_batch


def test_overhead_poses_look_down_and_keep_the_airplane_in_frame():
    K = intrinsics(640, 400, 70.0)
    R, t = overhead_poses(500, 0)
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    V = project_batch(airliner_keypoints(), R, t, K)
    assert np.all((V[..., 0] >= 0) & (V[..., 0] <= 639) & (V[..., 1] >= 0) & (V[..., 1] <= 399))
    # object z (up) points against the camera's viewing direction within the tilt bound
    up_in_cam = R[:, :, 2]
    tilt = np.degrees(np.arccos(-up_in_cam[:, 2]))
    assert tilt.max() <= 20.0 + 1e-9
    altitude = -(R.transpose(0, 2, 1) @ t[..., None])[:, 2, 0]  # camera centre height
    assert np.all((altitude >= 60 - 1e-9) & (altitude <= 80 + 1e-9))
    roll = euler_from_matrix(R)[:, 0]
    assert np.all(np.abs(np.abs(roll) - 180) < 21)  # nadir view: roll near ±180°


def test_same_seed_same_poses():
    a = overhead_poses(10, 3)
    b = overhead_poses(10, 3)
    c = overhead_poses(10, 4)
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.allclose(a[1], c[1])


def test_intrinsics_principal_point_at_pixel_centre():
    K = intrinsics(640, 400, 90.0)
    np.testing.assert_allclose(K, [[320, 0, 319.5], [0, 320, 199.5], [0, 0, 1]])


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: intrinsics(0, 400, 70), "width"),
        (lambda: intrinsics(640, 400, 180), "hfov_deg"),
        (lambda: overhead_poses(0, 0), "n"),
        (lambda: overhead_poses(5, 0, altitude=(80, 60)), "altitude"),
        (lambda: overhead_poses(5, 0, tilt_max_deg=95), "tilt_max_deg"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        call()
