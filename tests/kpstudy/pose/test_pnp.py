"""kpstudy.pose.pnp: poses recovered as OpenCV recovers them, one at a time and batched;
its guards (issue 29, point 4): argument checks, and poses that PnP flags as not valid (a
point behind the camera, a run-away residual, collinear keypoints)."""

import pickle

import cv2
import numpy as np
import pytest
import torch

from kpstudy.pose.geometry import project, project_batch
from kpstudy.pose.pnp import _CV_CRITERIA, PnPResult, solve_pnp, solve_pnp_batch
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


@pytest.fixture(scope="module")
def batch(P, K):
    return views(6, 21, K, P, noise_px=1.0)


@pytest.mark.parametrize("chunk", [0, -1, 2.5, True])
def test_chunk_must_be_a_positive_integer(P, K, batch, chunk):
    R, t, V = batch
    with pytest.raises(ValueError, match="^chunk: expected an integer >= 1"):
        solve_pnp_batch(P, V, K, (R, t), chunk=chunk)


def test_max_iter_must_be_a_positive_integer(P, K, batch):
    R, t, V = batch
    with pytest.raises(ValueError, match="^max_iter: expected an integer >= 1, got 0"):
        solve_pnp_batch(P, V, K, (R, t), max_iter=0)


@pytest.mark.parametrize("tol", [float("nan"), float("inf"), -1.0, "1e-7"])
def test_tol_px_must_be_finite_and_non_negative(P, K, batch, tol):
    R, t, V = batch
    with pytest.raises(ValueError, match="^tol_px: expected a finite number >= 0"):
        solve_pnp_batch(P, V, K, (R, t), tol_px=tol)


def test_initial_rotations_must_be_rotations(P, K, batch):
    R, t, V = batch
    scaled = R.copy()
    scaled[3] *= 2.0  # det 8
    with pytest.raises(ValueError, match=r"^init\[0\]: expected rotation matrices .*problem 3"):
        solve_pnp_batch(P, V, K, (scaled, t))
    with pytest.raises(ValueError, match=r"^init\[0\]: expected rotation matrices"):
        solve_pnp_batch(P, V, K, (-R[0], t[0]))  # orthonormal, det −1


def test_initial_pose_behind_the_camera_is_refused(P, K, batch):
    R, t, V = batch
    with pytest.raises(ValueError, match=r"^init: expected poses with every point in front"):
        solve_pnp_batch(P, V, K, (R, -t))
    with pytest.raises(ValueError, match=r"^init: expected a pose with every point in front"):
        solve_pnp(P, V[0], K, init=(R[0], -t[0]))


def test_max_rms_px_must_be_positive(P, K, batch):
    R, t, V = batch
    for bad in (0.0, -1.0, float("nan"), "2"):
        with pytest.raises(ValueError, match="^max_rms_px: expected a number > 0"):
            solve_pnp_batch(P, V, K, (R, t), max_rms_px=bad)
        with pytest.raises(ValueError, match="^max_rms_px: expected a number > 0"):
            solve_pnp(P, V[0], K, max_rms_px=bad)


@pytest.mark.parametrize("shape", ["one point", "a line"])
def test_degenerate_keypoints_are_flagged_not_solved(P, K, batch, shape):
    """Before: identical keypoints gave t ≈ 10⁸ m as a pose. After: that problem alone is
    flagged as not valid."""
    R, t, V = batch
    V = V.copy()
    if shape == "one point":
        V[2] = V[2, 0]  # all 23 keypoints at one pixel
    else:
        V[2] = V[2, 0] + np.linspace(0.0, 1.0, 23)[:, None] * np.array([120.0, 45.0])
    R_hat, t_hat = pose = solve_pnp_batch(P, V, K, (R, t))
    assert isinstance(pose, PnPResult) and R_hat.shape == (6, 3, 3) and t_hat.shape == (6, 3)
    assert pose.valid.tolist() == [True, True, False, True, True, True]


def test_batch_flags_poses_behind_the_camera_and_run_away_residuals(P, K):
    """Keypoints of a mirrored object (the views' points behind the camera), solved from the
    true (front) poses: LM ends either behind the camera or runs off towards t → ∞ with a
    residual near the keypoints' spread. Every such pose is flagged; good ones are not."""
    R, t, V = views(40, 3, K, P)
    mirrored = project_batch(P, R, -t, K)
    pose = solve_pnp_batch(P, mirrored, K, (R, t))
    behind = pose.min_depth <= 0
    run_away = np.abs(pose.t[:, 2]) > 1e4
    assert behind.any() and run_away.any()
    assert not pose.valid[behind | run_away].any()
    depth = np.einsum("bij,nj->bni", pose.R, P)[..., 2] + pose.t[:, None, 2]
    np.testing.assert_allclose(pose.min_depth, depth.min(1))
    good = solve_pnp_batch(P, V, K, (R, t))
    assert good.valid.all() and good.rms_px.max() < 1e-6


def test_solve_pnp_flags_a_pose_behind_the_camera(P, K):
    """Before: solve_pnp returned a pose with points behind the camera as any other."""
    R, t, _ = views(40, 3, K, P)
    mirrored = project_batch(P, R, -t, K)
    poses = [solve_pnp(P, v, K, init=(r, t_)) for v, r, t_ in zip(mirrored, R, t)]
    behind = [p for p in poses if p.min_depth <= 0]
    assert behind and not any(p.valid for p in behind)
    assert all(isinstance(p.valid, bool) for p in poses)


def test_max_rms_px_flags_residuals_far_above_the_noise(P, K):
    R, t, V = views(4, 22, K, P, noise_px=1.0)
    V = V.copy()
    V[1, :5] += 40.0  # five keypoints 57 px off
    pose = solve_pnp_batch(P, V, K, (R, t), max_rms_px=5.0)
    assert pose.valid.tolist() == [True, False, True, True]
    single = solve_pnp(P, V[1], K, max_rms_px=5.0)
    assert not single.valid and single.rms_px > 5.0


def test_result_unpacks_pickles_and_keeps_tensors(P, K, batch):
    R, t, V = batch
    pose = solve_pnp_batch(P, torch.from_numpy(V), K, (R, t))
    R_hat, t_hat = pose
    assert isinstance(pose.valid, torch.Tensor) and pose.valid.dtype == torch.bool
    assert R_hat is pose.R and t_hat is pose.t and len(pose) == 2
    again = pickle.loads(pickle.dumps(pose))
    assert torch.equal(again.R, pose.R) and torch.equal(again.valid, pose.valid)
