"""kpstudy.pose.sensitivity: the pose's first-order sensitivity to keypoint motion, against
finite differences of re-solved PnP."""

import numpy as np
import pytest

from kpstudy.pose.geometry import euler_from_matrix
from kpstudy.pose.pnp import solve_pnp, solve_pnp_batch
from kpstudy.pose.sensitivity import pose_sensitivity
from tests.conftest import HEATMAP_SCALE, views


def finite_differences(P, V, K, R, t, h=0.1):
    """Five-point central differences of re-solved PnP, (6, 2N), O(h⁴) truncation."""
    n = V.size
    D = np.eye(n).reshape(n, *V.shape)
    xi0 = np.r_[euler_from_matrix(R), t]

    def xi(step):  # ξ(V + step·e_j) − ξ(V) for every j, (2N, 6), angles unwrapped
        R_, t_ = solve_pnp_batch(P, V[None] + step * D, K, (R, t))
        d = np.c_[euler_from_matrix(R_), t_] - xi0
        d[:, :3] = (d[:, :3] + 180.0) % 360.0 - 180.0
        return d

    return ((8 * (xi(h) - xi(-h)) - (xi(2 * h) - xi(-2 * h))) / (12 * h)).T


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_equals_finite_differences(P, K, seed):
    _, _, V = views(1, 20 + seed, K, P, noise_px=1.5)
    R, t = solve_pnp(P, V[0], K)
    M = pose_sensitivity(P, V[0], K, R, t)
    FD = finite_differences(P, V[0], K, R, t)
    assert M.shape == (6, 46)
    rel = np.abs(M - FD) / np.abs(M).max(axis=1, keepdims=True)
    assert rel.max() <= 1e-4


def test_heatmap_scale_divides_columns(P, K):
    _, _, V = views(1, 30, K, P)
    R, t = solve_pnp(P, V[0], K)
    M = pose_sensitivity(P, V[0], K, R, t)
    Mh = pose_sensitivity(P, V[0], K, R, t, scale=HEATMAP_SCALE)
    np.testing.assert_allclose(Mh[:, 0::2], M[:, 0::2] / HEATMAP_SCALE[0])
    np.testing.assert_allclose(Mh[:, 1::2], M[:, 1::2] / HEATMAP_SCALE[1])


def test_linear_prediction_of_small_keypoint_motion(P, K):
    _, _, V = views(1, 31, K, P)
    R, t = solve_pnp(P, V[0], K)
    M = pose_sensitivity(P, V[0], K, R, t)
    dv = np.random.default_rng(0).normal(0, 0.01, V[0].shape)
    R2, t2 = solve_pnp(P, V[0] + dv, K, init=(R, t))
    dxi = np.r_[euler_from_matrix(R2) - euler_from_matrix(R), t2 - t]
    dxi[:3] = (dxi[:3] + 180) % 360 - 180
    np.testing.assert_allclose(M @ dv.ravel(), dxi, atol=1e-3 * np.abs(dxi).max())


def test_refuses_a_pose_that_is_not_the_optimum(P, K):
    R, t, V = views(1, 32, K, P, noise_px=2.0)
    with pytest.raises(ValueError, match="^R, t:"):
        pose_sensitivity(P, V[0], K, R[0], t[0])  # ground truth, not the PnP optimum


def test_singular_hessian(K):
    # four coplanar points symmetric about the optical axis, seen head-on, are fine;
    # but a planar set observed edge-on is singular: all points on a line through the centre
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    R = np.eye(3)
    t = np.array([0.0, 0.0, 1e9])  # at infinity: depth unobservable → singular
    V = np.array([[319.5, 199.5]] * 4) + np.array([[0, 0], [1e-6, 0], [0, 1e-6], [1e-6, 1e-6]])
    with pytest.raises(ValueError, match="^(P|V):"):
        pose_sensitivity(P, V, K, R, t)


def test_bad_input(P, K):
    R, t = np.eye(3), np.zeros(3)
    with pytest.raises(ValueError, match="^V:"):
        pose_sensitivity(P, np.zeros((22, 2)), K, R, t)
    with pytest.raises(ValueError, match="^scale:"):
        _, _, V = views(1, 33, K, P)
        R, t = solve_pnp(P, V[0], K)
        pose_sensitivity(P, V[0], K, R, t, scale=(0.1, 0.0))
