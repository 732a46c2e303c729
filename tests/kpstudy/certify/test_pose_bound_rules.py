"""kpstudy.certify.pose_bound_rules: the linearised pose bound over keypoint regions
against brute force, the single moves that alone leave the tolerance, the enumeration's
arguments, and poses that PnP flags."""

import itertools

import numpy as np
import pytest

from kpstudy.certify import pose_bound_rules
from kpstudy.certify import pose_bound_rules as rules
from kpstudy.certify.allocation_method import SeedImage
from kpstudy.certify.pose_bound_rules import linearised_bound
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T
from tests.conftest import views
from tests.helpers.pnp import flagged_pnp
from tests.helpers.pose_bound import far_tolerance, regions_with


def _random_sets(rng, K, most=5, spread=8.0):
    return [rng.normal(0, spread, (rng.integers(1, most + 1), 2)) for _ in range(K)]


@pytest.mark.parametrize("seed", range(5))
def test_bound_equals_brute_force_on_small_cases(seed):
    rng = np.random.default_rng(seed)
    K = 3
    M = rng.normal(size=(6, 2 * K))
    sets = _random_sets(rng, K, most=4)
    combos = np.array(
        [np.concatenate(c) for c in itertools.product(*sets)]
    )  # (Π n_k, 2K): every combination
    brute = np.abs(combos @ M.T).max(0)
    bound, extremes = linearised_bound(M, sets)
    np.testing.assert_allclose(bound, brute, rtol=1e-12, atol=1e-12)
    # The extreme picks attain the maximum of each signed axis.
    for axis in range(6):
        for sign, row in ((1, extremes[2 * axis]), (-1, extremes[2 * axis + 1])):
            value = sign * M[axis] @ np.concatenate([s[i] for s, i in zip(sets, row)])
            assert value == pytest.approx(
                sign * (combos @ M[axis]).max() if sign > 0 else -(combos @ M[axis]).min(),
                rel=1e-12,
            )


@pytest.mark.parametrize("seed", range(3))
def test_bound_covers_sampled_combinations_and_beats_the_triangle_bound(seed):
    rng = np.random.default_rng(10 + seed)
    K = 23
    M = rng.normal(size=(6, 2 * K)) * 0.05
    sets = _random_sets(rng, K, most=30)
    bound, _ = linearised_bound(M, sets)
    picks = [s[rng.integers(0, len(s), 4000)] for s in sets]  # (4000, 2) per keypoint
    delta = np.concatenate(picks, axis=1)  # (4000, 2K) in u1, v1, u2, … order
    assert np.all(np.abs(delta @ M.T) <= bound + 1e-12)
    largest = np.concatenate([np.abs(s).max(0) for s in sets])  # max |δ_j| per coordinate
    assert np.all(bound <= np.abs(M) @ largest + 1e-12)


@pytest.mark.parametrize("alpha", [0.5, 1.0, 2.0])
def test_regions_inside_the_allocated_cells_keep_the_allocation_verdict(alpha):
    """With ground truth on pixel centres, any region inside the allocated cells gives a
    bound inside Ξ: the pose-bound method verifies whatever the allocation verifies."""
    rng = np.random.default_rng(int(alpha * 10))
    K, factor = 23, 10.0  # image px per heatmap px
    M_heatmap = rng.normal(size=(6, 2 * K)) * np.r_[[1.0] * 3, [0.3] * 3][:, None]
    eps = alpha * np.r_[EPS_R, EPS_T]
    dv = allocate_tolerances(M_heatmap, eps[:3], eps[3:], max_dv=64).dv  # (K, 2)
    sets = []
    for du, dv_ in dv:
        cell = np.array([(u, v) for u in range(-du, du + 1) for v in range(-dv_, dv_ + 1)])
        keep = rng.random(len(cell)) < 0.6
        keep[rng.integers(len(cell))] = True
        sets.append(cell[keep] * factor)  # image-pixel deviations
    bound, _ = linearised_bound(M_heatmap / factor, sets)
    assert np.all(bound <= eps + 1e-9)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="^M"):
        linearised_bound(np.zeros((6, 4)), [np.zeros((1, 2))])
    with pytest.raises(ValueError, match=r"^deviations\[1\]"):
        linearised_bound(np.zeros((6, 4)), [np.zeros((1, 2)), np.zeros((0, 2))])


def test_single_moves_are_the_possible_pixels_that_alone_leave_the_tolerance(scene):
    seed, R, t, factors, centers = scene
    eps, _ = far_tolerance(scene)
    pixels = regions_with(centers, [(0, (8, 0)), (0, (1, 0)), (3, (0, 1))])
    moves = rules.single_moves(
        seed, [np.asarray(p, float) for p in pixels], centers, factors, R, t, eps
    )
    assert [(k, tuple(p)) for k, p in moves] == [(0, tuple(centers[0] + [8, 0]))]
    wide = np.full(6, 1e6)
    assert (
        rules.single_moves(
            seed, [np.asarray(p, float) for p in pixels], centers, factors, R, t, wide
        )
        == []
    )


def test_bad_chunks_and_keypoints_are_named(scene):
    seed, R, t, _, _ = scene
    with pytest.raises(ValueError, match="^chunk"):
        rules.enumerated_pose_error(seed, [np.zeros((1, 2))] * 23, R, t, chunk=0)
    with pytest.raises(ValueError, match=r"^keypoints\[1\]"):
        rules.enumerated_pose_error(seed, [np.zeros((1, 2)), np.zeros((0, 2))], R, t)


def test_a_pose_that_pnp_flags_has_an_infinite_error(P, K, monkeypatch):
    R, t, V = views(3, 25, K, P)
    seed = SeedImage(0, V[0], K, P, (640, 400))
    monkeypatch.setattr(pose_bound_rules, "solve_pnp_batch", flagged_pnp(False))
    assert np.isinf(pose_bound_rules.pnp_pose_errors(seed, V, R[0], t[0])).all()
    monkeypatch.setattr(pose_bound_rules, "solve_pnp_batch", flagged_pnp(True))
    assert np.all(pose_bound_rules.pnp_pose_errors(seed, V[:1], R[0], t[0]) == 0)
