import cv2
import numpy as np
import pytest
import torch

from kpstudy.pose.geometry import project, project_batch
from kpstudy.pose.pnp import _CV_CRITERIA, solve_pnp, solve_pnp_batch
from tests.conftest import views


def test_recovers_known_poses_noise_free(P, K):
    R, t, V = views(50, 10, K, P)
    for Ri, ti, Vi in zip(R, t, V):
        R_hat, t_hat = solve_pnp(P, Vi, K)
        np.testing.assert_allclose(R_hat, Ri, atol=1e-6)
        np.testing.assert_allclose(t_hat, ti, atol=1e-6)


def test_matches_opencv_iterative_on_noisy_problems(P, K):
    _, _, V = views(30, 11, K, P, noise_px=3.0)
    for Vi in V:
        R_hat, t_hat = solve_pnp(P, Vi, K)
        ok, rvec, tvec = cv2.solvePnP(P, Vi, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
        rvec, tvec = cv2.solvePnPRefineLM(P, Vi, K, None, rvec, tvec, criteria=_CV_CRITERIA)
        np.testing.assert_allclose(R_hat, cv2.Rodrigues(rvec)[0], atol=1e-6)
        np.testing.assert_allclose(t_hat, tvec.ravel(), atol=1e-5)


def test_refinement_from_init_stays_at_optimum(P, K):
    R, t, V = views(10, 12, K, P, noise_px=2.0)
    for Vi in V:
        R0, t0 = solve_pnp(P, Vi, K)
        R1, t1 = solve_pnp(P, Vi, K, init=(R0, t0))
        np.testing.assert_allclose(R1, R0, atol=1e-9)
        np.testing.assert_allclose(t1, t0, atol=1e-7)


def test_batch_agrees_with_opencv_on_1000_problems(P, K):
    R, t, V = views(1000, 13, K, P, noise_px=2.0)
    R_b, t_b = solve_pnp_batch(P, V, K, (R, t))
    for i in range(1000):
        R_cv, t_cv = solve_pnp(P, V[i], K)
        np.testing.assert_allclose(R_b[i], R_cv, atol=1e-6)
        np.testing.assert_allclose(t_b[i], t_cv, atol=1e-5)
        # our optimum is at least as good as OpenCV's
        ours, theirs = (
            ((project_batch(P, R_, t_, K) - V[i]) ** 2).sum()
            for R_, t_ in ((R_b[i], t_b[i]), (R_cv, t_cv))
        )
        assert ours <= theirs * (1 + 1e-12)


def test_batch_tensor_in_tensor_out_and_broadcasting(P, K):
    R, t, V = views(8, 14, K, P, noise_px=1.0)
    R0, t0 = solve_pnp(P, V[0], K)
    R_b, t_b = solve_pnp_batch(
        torch.from_numpy(P),
        torch.from_numpy(V),
        torch.from_numpy(K),
        (torch.from_numpy(R0), torch.from_numpy(t0)),
    )
    assert isinstance(R_b, torch.Tensor) and R_b.shape == (8, 3, 3) and t_b.shape == (8, 3)
    R_np, t_np = solve_pnp_batch(P, V, np.broadcast_to(K, (8, 3, 3)), (R, t), chunk=3)
    np.testing.assert_allclose(R_b.numpy(), R_np, atol=1e-8)
    np.testing.assert_allclose(t_b.numpy(), t_np, atol=1e-6)


def test_batch_recovers_far_from_init(P, K):
    """LM damping: a 10° / 5 m initial error still converges to the true pose."""
    from scipy.spatial.transform import Rotation

    R, t, V = views(200, 15, K, P)
    kick = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 0.1, (200, 3))).as_matrix()
    R_b, t_b = solve_pnp_batch(P, V, K, (kick @ R, t + 3.0))
    np.testing.assert_allclose(R_b, R, atol=1e-6)
    np.testing.assert_allclose(t_b, t, atol=1e-5)


@pytest.mark.slow
def test_compiled_batch_equals_eager(P, K):
    R, t, V = views(64, 16, K, P, noise_px=2.0)
    eager = solve_pnp_batch(P, V, K, (R, t))
    fused = solve_pnp_batch(P, V, K, (R, t), compile=True)
    np.testing.assert_allclose(fused[0], eager[0], atol=1e-7)
    np.testing.assert_allclose(fused[1], eager[1], atol=1e-5)


_rand = np.random.default_rng(0).random


@pytest.mark.parametrize(
    "P_, V_, name",
    [
        (np.ones((3, 3)), np.ones((3, 2)), "P"),  # fewer than 4 points
        (np.ones((5, 3)), np.ones((4, 2)), "V"),  # mismatched counts
        (np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)], _rand((5, 2)), "P"),  # collinear
        (_rand((5, 3)), np.c_[np.arange(5.0), np.arange(5.0)], "V"),  # collinear image
        (_rand((5, 3)), np.full((5, 2), np.nan), "V"),
        (_rand((5, 3)) * np.array([1, 1, np.inf]), _rand((5, 2)), "P"),
    ],
)
def test_bad_input(P_, V_, name, K):
    with pytest.raises(ValueError, match=f"^{name}:"):
        solve_pnp(P_, V_, K)


def test_bad_init_and_batch_input(P, K):
    V = project(P, np.diag([1.0, -1.0, -1.0]), [0, 0, 70.0], K)
    with pytest.raises(ValueError, match="^init"):
        solve_pnp(P, V, K, init=np.eye(3))
    with pytest.raises(ValueError, match="^init"):
        solve_pnp(P, V, K, init=(np.eye(3) * 2, np.zeros(3)))
    with pytest.raises(ValueError, match="^V:"):
        solve_pnp_batch(P, V, K, (np.eye(3), np.zeros(3)))  # (N, 2) is not a batch
    with pytest.raises(ValueError, match="^P:"):
        solve_pnp_batch(P[:5], V[None], K, (np.eye(3), np.zeros(3)))
    with pytest.raises(ValueError, match="^K:"):
        solve_pnp_batch(P, V[None], -K, (np.eye(3), np.zeros(3)))
