"""kpstudy.pose.pnp's guards (issue 29, point 4): argument checks, and poses that PnP flags as not
valid (a point behind the camera, a run-away residual, collinear keypoints), which no
caller counts as inside Ξ."""

import pickle

import numpy as np
import pytest
import torch

from kpstudy.certify import pose_bound_rules
from kpstudy.models.evaluation import pose_errors
from kpstudy.pose import montecarlo
from kpstudy.pose.geometry import EPS_R, EPS_T, project_batch
from kpstudy.pose.montecarlo import probabilistic_soundness, soundness_completeness_table
from kpstudy.pose.pnp import PnPResult, solve_pnp, solve_pnp_batch
from tests.conftest import views


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


def _flagged(valid: bool):
    """A stand-in batched PnP: the initial pose itself (zero error), ``valid`` as given."""

    def solve(P, V, K, init, **kw):
        n = len(V)
        R = np.broadcast_to(np.asarray(init[0], float), (n, 3, 3)).copy()
        t = np.broadcast_to(np.asarray(init[1], float), (n, 3)).copy()
        out = (R, t, np.full(n, valid), np.zeros(n), np.ones(n))
        if isinstance(V, torch.Tensor):
            out = tuple(torch.from_numpy(x) for x in out)
        return PnPResult(*out)

    return solve


def test_montecarlo_never_counts_a_flagged_pose_inside(P, K, monkeypatch):
    R, t, V = views(2, 23, K, P)
    dv = np.full(V.shape, 0.5)
    args = (P, V, K, R, t, dv, EPS_R, EPS_T)
    monkeypatch.setattr(montecarlo, "solve_pnp_batch", _flagged(True))
    assert probabilistic_soundness(*args, n_samples=8, seed=0).tolist() == [1.0, 1.0]
    monkeypatch.setattr(montecarlo, "solve_pnp_batch", _flagged(False))
    assert probabilistic_soundness(*args, n_samples=8, seed=0).tolist() == [0.0, 0.0]


def test_montecarlo_refuses_an_invalid_nominal_pose(P, K, monkeypatch):
    _, _, V = views(2, 24, K, P)
    real = montecarlo.solve_pnp

    def flag_second(P_, V_, K_, *a, **kw):
        pose = real(P_, V_, K_, *a, **kw)
        bad = np.array_equal(V_, V[1])
        return PnPResult(*pose, not bad, pose.rms_px, pose.min_depth)

    monkeypatch.setattr(montecarlo, "solve_pnp", flag_second)
    with pytest.raises(ValueError, match="^V: PnP on the keypoints of image 1 gives no valid"):
        soundness_completeness_table(P, V, K, kappas=[1.0], alphas=[1.0], n_samples=2, seed=0)


def test_pose_bound_and_evaluate_give_flagged_poses_an_infinite_error(P, K, monkeypatch):
    from kpstudy.certify.allocation_method import SeedImage
    from kpstudy.models import evaluation as evaluate_module

    R, t, V = views(3, 25, K, P)
    seed = SeedImage(0, V[0], K, P, (640, 400))
    monkeypatch.setattr(pose_bound_rules, "solve_pnp_batch", _flagged(False))
    assert np.isinf(pose_bound_rules.pnp_pose_errors(seed, V, R[0], t[0])).all()
    monkeypatch.setattr(pose_bound_rules, "solve_pnp_batch", _flagged(True))
    assert np.all(pose_bound_rules.pnp_pose_errors(seed, V[:1], R[0], t[0]) == 0)

    def flagged_single(P_, V_, K_, init=None, **kw):
        return PnPResult(R[0], t[0], False, 0.0, 1.0)

    monkeypatch.setattr(evaluate_module, "solve_pnp", flagged_single)
    assert np.isinf(pose_errors(P, V, np.stack([K] * 3), R, t)).all()


def test_certify_refuses_a_seed_without_a_valid_nominal_pose(P, K, monkeypatch):
    from kpstudy.certify import allocation_method
    from kpstudy.certify.allocation_method import SeedImage
    from kpstudy.certify.hull import certify

    R, t, V = views(1, 26, K, P)
    monkeypatch.setattr(
        allocation_method, "solve_pnp", lambda *a, **kw: PnPResult(R[0], t[0], False, 90.0, -3.0)
    )
    backbone = torch.nn.Identity()
    backbone.input_size, backbone.heatmap_size = 64, 64
    seed = SeedImage(0, V[0], K, P, (640, 400))
    with pytest.raises(ValueError, match="^seed: PnP on the ground-truth keypoints gives no"):
        certify(backbone, np.zeros((2, 8, 8, 3)), seed, check_samples=0)
