"""kpstudy.pose.geometry: projection, Euler angles and pose errors, against OpenCV and SciPy."""

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kpstudy.pose.geometry import (
    euler_from_matrix,
    euler_from_matrix_torch,
    matrix_from_euler,
    matrix_from_euler_torch,
    pose_error,
    project,
    project_batch,
)
from tests.conftest import views


def test_project_equals_opencv(P, K):
    R, t, _ = views(20, 0, K, P)
    for Ri, ti in zip(R, t):
        ref = cv2.projectPoints(P, cv2.Rodrigues(Ri)[0], ti, K, None)[0].reshape(-1, 2)
        np.testing.assert_allclose(project(P, Ri, ti, K), ref, atol=1e-9)


def test_project_batch_numpy_and_torch_agree(P):
    K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 200.0], [0.0, 0.0, 1.0]])
    R = Rotation.random(5, random_state=1).as_matrix()
    t = np.tile([0.0, 0.0, 200.0], (5, 1))
    batch = project_batch(P, R, t, K)
    torch_batch = project_batch(
        torch.from_numpy(P), torch.from_numpy(R), torch.from_numpy(t), torch.from_numpy(K)
    ).numpy()
    for i in range(5):
        ref = cv2.projectPoints(P, cv2.Rodrigues(R[i])[0], t[i], K, None)[0].reshape(-1, 2)
        np.testing.assert_allclose(batch[i], ref, atol=1e-9)
    np.testing.assert_allclose(torch_batch, batch, atol=1e-12)


def test_euler_round_trip_and_scipy_convention():
    e = np.array([[30.0, -20.0, 170.0], [-179.0, 5.0, -90.0], [0.0, 0.0, 0.0]])
    R = matrix_from_euler(e)
    np.testing.assert_allclose(euler_from_matrix(R), e, atol=1e-10)
    # extrinsic xyz: R = Rz(yaw) Ry(pitch) Rx(roll)
    Rz, Ry, Rx = (
        Rotation.from_euler(a, v, degrees=True).as_matrix() for a, v in zip("zyx", e[0][::-1])
    )
    np.testing.assert_allclose(R[0], Rz @ Ry @ Rx, atol=1e-12)


def test_torch_euler_matches_scipy():
    e = Rotation.random(500, random_state=2).as_euler("xyz", degrees=True)
    e = e[np.abs(e[:, 1]) < 89.0]
    R = matrix_from_euler(e)
    np.testing.assert_allclose(matrix_from_euler_torch(torch.from_numpy(e)).numpy(), R, atol=1e-12)
    np.testing.assert_allclose(
        euler_from_matrix_torch(torch.from_numpy(R)).numpy(), euler_from_matrix(R), atol=1e-9
    )


def test_pose_error_wraps_around():
    dr, dt = pose_error(
        matrix_from_euler([179.0, 10.0, -170.0]),
        [1.0, 2.0, 3.0],
        matrix_from_euler([-179.0, 10.0, 175.0]),
        [1.5, 2.0, 1.0],
    )
    np.testing.assert_allclose(dr, [2.0, 0.0, 15.0], atol=1e-9)
    np.testing.assert_allclose(dt, [0.5, 0.0, 2.0])
    assert np.all((dr >= 0) & (dr <= 180))


def test_pose_error_is_zero_on_itself_and_symmetric():
    R = Rotation.random(1, random_state=3).as_matrix()[0]
    R2 = Rotation.random(1, random_state=4).as_matrix()[0]
    assert np.allclose(pose_error(R, np.zeros(3), R, np.zeros(3))[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(
        pose_error(R, np.zeros(3), R2, np.ones(3))[0],
        pose_error(R2, np.ones(3), R, np.zeros(3))[0],
        atol=1e-9,
    )


@pytest.mark.parametrize(
    "args, name",
    [
        (dict(P=np.zeros((4, 2))), "P"),
        (dict(P=np.full((4, 3), np.nan)), "P"),
        (dict(R=np.eye(3) * 2), "R"),
        (dict(t=np.zeros(2)), "t"),
        (dict(t=np.array([0.0, 0.0, np.inf])), "t"),
        (dict(K=np.eye(3) * -1), "K"),
        (dict(K=np.array([[100.0, 2.0, 32], [0, 100, 24], [0, 0, 1]])), "K"),  # skew
        (dict(t=np.array([0.0, 0.0, -10.0])), "P"),  # behind the camera
    ],
)
def test_project_bad_input(args, name):
    base = dict(
        P=np.ones((4, 3)),
        R=np.eye(3),
        t=np.array([0.0, 0.0, 10.0]),
        K=np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]),
    )
    base.update(args)
    with pytest.raises(ValueError, match=f"^{name}:"):
        project(**base)


def test_euler_bad_input():
    with pytest.raises(ValueError, match="^e:"):
        matrix_from_euler([1.0, 2.0])
    with pytest.raises(ValueError, match="^R:"):
        euler_from_matrix(np.full((3, 3), np.nan))
