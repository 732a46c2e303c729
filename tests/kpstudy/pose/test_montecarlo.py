"""kpstudy.pose.montecarlo: probabilistic soundness and completeness of allocated
tolerances, against OpenCV and direct projection; a pose that PnP flags is never counted
inside Ξ."""

import numpy as np
import pytest

from kpstudy.pose import montecarlo
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T, euler_from_matrix, project, wrap_degrees
from kpstudy.pose.montecarlo import (
    SOUNDNESS_TOL_PX,
    _rng,
    probabilistic_completeness,
    probabilistic_soundness,
    soundness_completeness_table,
)
from kpstudy.pose.pnp import PnPResult, solve_pnp
from kpstudy.pose.sensitivity import pose_sensitivity
from tests.conftest import HEATMAP_SCALE, views
from tests.helpers.pnp import flagged_pnp


@pytest.fixture(scope="module")
def study(P, K):
    """Six overhead views (60–80 m altitude): GT keypoints, nominal poses, sensitivities."""
    _, _, V = views(6, 40, K, P)
    poses = [solve_pnp(P, v, K) for v in V]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    M = [pose_sensitivity(P, v, K, r, t_, scale=HEATMAP_SCALE) for v, r, t_ in zip(V, R, t)]
    return V, R, t, M


def allocate(M, alpha, kappa=1.0):
    return np.stack(
        [allocate_tolerances(m, alpha * EPS_R, alpha * EPS_T, kappa=kappa, max_dv=64).dv for m in M]
    )


def test_soundness_tends_to_one_as_alpha_shrinks(P, K, study):
    """Small α: the box shrinks to the keypoints themselves and soundness reaches 1.

    (At a finite α the optimal box touches the linearised boundary of Ξ, so vertices on
    it fall either side by the PnP's curvature: soundness < 1 is expected there.)
    """
    V, R, t, M = study
    fractions = []
    for alpha in (0.005, 0.1, 1.0):
        dv = allocate(M, alpha)
        s = probabilistic_soundness(
            P,
            V,
            K,
            R,
            t,
            dv,
            alpha * EPS_R,
            alpha * EPS_T,
            n_samples=300,
            seed=0,
            scale=HEATMAP_SCALE,
        )
        fractions.append(s.mean())
        if alpha == 0.005:
            assert dv.max() == 0
    assert fractions[0] == 1.0
    assert fractions[1] >= 0.9
    assert fractions[0] > fractions[2]


def test_soundness_non_decreasing_in_kappa(P, K, study):
    V, R, t, M = study
    s = [
        probabilistic_soundness(
            P,
            V,
            K,
            R,
            t,
            allocate(M, 1.0, kappa),
            EPS_R,
            EPS_T,
            n_samples=400,
            seed=1,
            scale=HEATMAP_SCALE,
        ).mean()
        for kappa in (1.0, 1.5, 2.0, 4.0)
    ]
    assert all(b >= a - 0.01 for a, b in zip(s, s[1:])), s
    assert s[-1] > s[0]


def test_soundness_equals_opencv_reference(P, K, study):
    """Same vertex draws, each re-solved with OpenCV: the same inside/outside decisions.

    (At large α the vertices move keypoints by up to ~100 px, the reprojection cost is
    flat along the bas-relief direction and both LM solvers stop at slightly different
    points; α = 0.5 keeps the problems well conditioned.)
    """
    V, R, t, M = study
    dv = allocate(M, 0.5)
    S = 60
    ours = probabilistic_soundness(
        P,
        V[:2],
        K,
        R[:2],
        t[:2],
        dv[:2],
        0.5 * EPS_R,
        0.5 * EPS_T,
        n_samples=S,
        seed=7,
        scale=HEATMAP_SCALE,
    )
    eps = 0.5 * np.r_[EPS_R, EPS_T]
    for i in range(2):
        signs = _rng(7, i).choice([-1.0, 1.0], size=(S, 23, 2))
        inside = []
        for a in signs:
            R_hat, t_hat = solve_pnp(
                P, V[i] + a * dv[i] / np.asarray(HEATMAP_SCALE), K, init=(R[i], t[i])
            )
            d = np.r_[
                wrap_degrees(euler_from_matrix(R_hat) - euler_from_matrix(R[i])),
                np.abs(t_hat - t[i]),
            ]
            inside.append(np.all(d <= eps))
        assert ours[i] == pytest.approx(np.mean(inside), abs=1e-12)


def test_soundness_tolerance_does_not_change_decisions(P, K, study):
    """The Monte Carlo's looser stopping tolerance gives the fractions of a tight one."""
    V, R, t, M = study
    args = (P, V, K, R, t, allocate(M, 1.0), EPS_R, EPS_T)
    common = dict(n_samples=400, seed=5, scale=HEATMAP_SCALE)
    assert SOUNDNESS_TOL_PX > 1e-7
    loose = probabilistic_soundness(*args, **common)
    tight = probabilistic_soundness(*args, tol_px=1e-7, **common)
    np.testing.assert_array_equal(loose, tight)


def test_completeness_matches_direct_projection(P, K, study):
    V, R, t, M = study
    dv = allocate(M, 2.0)
    eps = 2.0 * np.r_[EPS_R, EPS_T]
    S = 200
    ours = probabilistic_completeness(
        P, V[:2], K, R[:2], t[:2], dv[:2], eps[:3], eps[3:], n_samples=S, seed=3
    )  # dv read as image pixels
    for i in range(2):
        dxi = _rng(3, i).uniform(-1.0, 1.0, (S, 6)) * eps
        e0 = euler_from_matrix(R[i])
        inside = []
        for d in dxi:
            from kpstudy.pose.geometry import matrix_from_euler

            Vs = project(P, matrix_from_euler(e0 + d[:3]), t[i] + d[3:], K)
            inside.append(np.all(np.abs(Vs - V[i]) <= dv[i]))
        assert ours[i] == pytest.approx(np.mean(inside), abs=1e-12)


def test_completeness_extremes(P, K, study):
    V, R, t, _ = study
    zero = np.zeros((6, 23, 2))
    huge = np.full((6, 23, 2), 1e4)
    args = (P, V, K, R, t)
    assert probabilistic_completeness(*args, zero, EPS_R, EPS_T, n_samples=50, seed=0).max() == 0
    assert probabilistic_completeness(*args, huge, EPS_R, EPS_T, n_samples=50, seed=0).min() == 1
    # soundness of a zero box: the keypoints do not move, the pose is the nominal one
    assert probabilistic_soundness(*args, zero, EPS_R, EPS_T, n_samples=20, seed=0).min() == 1


def test_chunking_and_seed_determinism(P, K, study):
    V, R, t, M = study
    dv = allocate(M, 1.0)
    a = probabilistic_soundness(
        P, V, K, R, t, dv, EPS_R, EPS_T, n_samples=50, seed=5, scale=HEATMAP_SCALE
    )
    b = probabilistic_soundness(
        P, V, K, R, t, dv, EPS_R, EPS_T, n_samples=50, seed=5, scale=HEATMAP_SCALE, chunk_images=1
    )
    np.testing.assert_array_equal(a, b)
    c = probabilistic_soundness(
        P, V, K, R, t, dv, EPS_R, EPS_T, n_samples=50, seed=6, scale=HEATMAP_SCALE
    )
    assert a.shape == (6,) and np.all((0 <= c) & (c <= 1))


def test_table_has_the_grid_and_trends(P, K):
    _, _, V = views(3, 41, K, P)
    df = soundness_completeness_table(
        P,
        V,
        K,
        kappas=(1.0, 2.0),
        alphas=(0.5, 1.0),
        n_samples=100,
        seed=0,
        scale=HEATMAP_SCALE,
        max_dv=64,
    )
    assert list(df.columns[:5]) == [
        "tolerance_units",
        "kappa",
        "alpha",
        "soundness",
        "completeness",
    ]
    assert len(df) == 4 and df.samples.iloc[0] == 300
    by = df.set_index(["kappa", "alpha"])
    assert by.loc[(2.0, 1.0), "mean_dv"] <= by.loc[(1.0, 1.0), "mean_dv"]
    assert by.loc[(1.0, 1.0), "mean_dv"] >= by.loc[(1.0, 0.5), "mean_dv"]


def test_both_readings_give_their_documented_allocations(P, K):
    _, _, V = views(2, 42, K, P)
    grid = dict(kappas=(1.0,), alphas=(1.0,), n_samples=50, seed=0, max_dv=64)
    heatmap = soundness_completeness_table(P, V, K, scale=HEATMAP_SCALE, **grid)
    paper = soundness_completeness_table(
        P, V, K, scale=HEATMAP_SCALE, tolerance_units="paper", **grid
    )
    poses = [solve_pnp(P, v, K) for v in V]
    R, t = np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])
    dv = {}
    for units, scale in (("heatmap", HEATMAP_SCALE), ("paper", None)):
        M = [pose_sensitivity(P, v, K, r, t_, scale=scale) for v, r, t_ in zip(V, R, t)]
        dv[units] = allocate(M, 1.0)
    assert heatmap.mean_dv[0] == dv["heatmap"].mean()
    assert paper.mean_dv[0] == dv["paper"].mean() > dv["heatmap"].mean()
    study = (P, V, K, R, t)
    common = dict(eps_r=EPS_R, eps_t=EPS_T, n_samples=50, seed=0)
    # The paper's reading: its own soundness in image pixels, and the same integer boxes
    # read as heatmap pixels (what the verifier proves).
    own = probabilistic_soundness(*study, dv["paper"], **common).mean()
    true = probabilistic_soundness(*study, dv["paper"], scale=HEATMAP_SCALE, **common).mean()
    assert paper.soundness[0] == own and paper.soundness_true_units[0] == true
    assert heatmap.soundness_true_units[0] == heatmap.soundness[0]
    with pytest.raises(ValueError, match="^tolerance_units:"):
        soundness_completeness_table(P, V, K, tolerance_units="pixels", **grid)


@pytest.mark.parametrize(
    "change, name",
    [
        (dict(n_samples=0), "n_samples"),
        (dict(dv=-np.ones((6, 23, 2))), "dv"),
        (dict(dv=np.ones((6, 22, 2))), "dv"),
        (dict(eps_r=np.zeros(3)), "eps_r"),
        (dict(eps_t=[1.0, 1.0]), "eps_t"),
        (dict(scale=(0.1, -1.0)), "scale"),
        (dict(K=np.eye(3) * 0), "K"),
    ],
)
def test_bad_input(P, K, study, change, name):
    V, R, t, _ = study
    kw = dict(
        P=P,
        V=V,
        K=K,
        R=R,
        t=t,
        dv=np.ones((6, 23, 2)),
        eps_r=EPS_R,
        eps_t=EPS_T,
        n_samples=10,
        seed=0,
    )
    kw.update(change)
    for fn in (probabilistic_soundness, probabilistic_completeness):
        with pytest.raises(ValueError, match=f"^{name}:"):
            fn(**kw)


def test_montecarlo_never_counts_a_flagged_pose_inside(P, K, monkeypatch):
    R, t, V = views(2, 23, K, P)
    dv = np.full(V.shape, 0.5)
    args = (P, V, K, R, t, dv, EPS_R, EPS_T)
    monkeypatch.setattr(montecarlo, "solve_pnp_batch", flagged_pnp(True))
    assert probabilistic_soundness(*args, n_samples=8, seed=0).tolist() == [1.0, 1.0]
    monkeypatch.setattr(montecarlo, "solve_pnp_batch", flagged_pnp(False))
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
