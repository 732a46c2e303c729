"""Tests for kpstudy.pose.allocation: exact integer tolerance allocation."""

from __future__ import annotations

import dataclasses

import cvxpy as cp
import numpy as np
import pytest

from kpstudy.pose import allocation
from kpstudy.pose.allocation import Allocation, allocate_tolerances

EPS_R = np.array([10.0, 10.0, 10.0])  # degrees

EPS_T = np.array([4.0, 4.0, 20.0])  # metres


def random_M(rng: np.random.Generator, K: int) -> np.ndarray:
    """(6, 2K) with realistic magnitudes: 1e-2..1e-1 deg/px, 1e-2..1 m/px, random signs."""
    rot = rng.uniform(1e-2, 1e-1, (3, 2 * K))
    trans = 10.0 ** rng.uniform(-2.0, 0.0, (3, 2 * K))
    return np.vstack([rot, trans]) * rng.choice([-1.0, 1.0], (6, 2 * K))


def feasible(M, eps, kappa, dv) -> bool:
    return bool(np.all(kappa * np.abs(M) @ np.asarray(dv).ravel() <= eps))


def objective(dv, w1, w2) -> float:
    x = np.asarray(dv).ravel()
    return float(w1 * np.sum(np.log(2.0 * x + 1.0)) + w2 * x.min())


def brute_force(M, eps, kappa, w1, w2, ub):
    """Best objective over all integer vectors 0 <= x <= ub with kappa|M|x <= eps."""
    X = np.indices([int(u) + 1 for u in ub]).reshape(len(ub), -1).T.astype(np.float64)
    ok = np.all(X @ (kappa * np.abs(M)).T <= eps, axis=1)
    X = X[ok]
    J = w1 * np.log(2.0 * X + 1.0).sum(axis=1) + w2 * X.min(axis=1)
    return J.max(), X


def small_instance(rng: np.random.Generator, K: int | None = None):
    """K = 1 or 2 (bounds <= 6) unless given (K = 3: <= 5, K = 4: <= 4); binding tolerances."""
    K = int(rng.integers(1, 3)) if K is None else K
    top = {1: 6, 2: 6, 3: 5, 4: 4}[K]
    M = random_M(rng, K)
    ub = rng.integers(0, top + 1, size=2 * K)
    ub[rng.integers(2 * K)] = top  # at least one coordinate with room
    eps = np.abs(M) @ ub * rng.uniform(0.15, 0.9, 6) + 1e-6
    return M, eps, ub


def check_valid(a: Allocation, M, eps, kappa, ub) -> None:
    K = M.shape[1] // 2
    assert isinstance(a, Allocation)
    assert a.dv.shape == (K, 2) and a.dv.dtype == np.int64
    assert a.relaxation_dv.shape == (K, 2) and a.relaxation_dv.dtype == np.float64
    assert feasible(M, eps, kappa, a.dv)
    assert np.all(a.dv >= 0) and np.all(a.dv.ravel() <= np.asarray(ub).ravel())
    assert a.delta == int(a.dv.min()) and isinstance(a.delta, int)
    assert a.status == "optimal"


@pytest.fixture(scope="module")
def k23():
    rng = np.random.default_rng(2024)
    M = random_M(rng, 23)
    return M, allocate_tolerances(M, EPS_R, EPS_T, max_dv=64)


def test_k23_feasible_integral_shapes(k23):
    M, a = k23
    eps = np.concatenate([EPS_R, EPS_T])
    check_valid(a, M, eps, 1.0, np.full(46, 64))
    assert a.objective == pytest.approx(objective(a.dv, 1.0, 5.0), abs=1e-12)
    assert a.kappa == 1.0
    np.testing.assert_array_equal(a.eps_r, EPS_R)
    np.testing.assert_array_equal(a.eps_t, EPS_T)
    assert a.dv.sum() > 0  # the budget is used
    assert "Allocation(K=23" in str(a)


def test_k23_maximal(k23):
    M, a = k23
    eps = np.concatenate([EPS_R, EPS_T])
    x = a.dv.ravel()
    for j in range(x.size):
        y = x.copy()
        y[j] += 1
        assert y[j] > 64 or not feasible(M, eps, 1.0, y), f"coordinate {j} could grow"


def test_k23_relaxation_bounds_objective(k23):
    M, a = k23
    assert a.relaxation_objective >= a.objective - 1e-9
    assert np.all(a.relaxation_dv >= 0) and np.all(a.relaxation_dv <= 64 + 1e-6)
    eps = np.concatenate([EPS_R, EPS_T])
    assert np.all(np.abs(M) @ a.relaxation_dv.ravel() <= eps * (1 + 1e-6))


@pytest.mark.parametrize("seed", range(6))
def test_maximal_medium(seed):
    rng = np.random.default_rng(100 + seed)
    M = random_M(rng, 6)
    eps = np.concatenate([EPS_R, EPS_T]) * rng.uniform(0.3, 1.0, 6)
    a = allocate_tolerances(M, eps[:3], eps[3:], kappa=1.5, w2=0.0, max_dv=20)
    check_valid(a, M, eps, 1.5, np.full(12, 20))
    x = a.dv.ravel()
    for j in range(x.size):
        y = x.copy()
        y[j] += 1
        assert y[j] > 20 or not feasible(M, eps, 1.5, y)


@pytest.mark.parametrize("seed", range(40))
def test_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    M, eps, ub = small_instance(rng)
    _check_against_brute_force(rng, M, eps, ub)


@pytest.mark.parametrize("seed", range(12))
def test_equals_brute_force_larger(seed):
    """6-8 coordinates: here a greedy point is often not optimal (the MILP must decide)."""
    rng = np.random.default_rng(1000 + seed)
    M, eps, ub = small_instance(rng, K=3 + seed % 2)
    _check_against_brute_force(rng, M, eps, ub)


def _check_against_brute_force(rng, M, eps, ub):
    kappa = float(rng.choice([1.0, 1.5, 2.0]))
    w1 = float(rng.uniform(0.5, 2.0))
    w2 = float(rng.choice([0.0, 5.0, rng.uniform(0.0, 3.0)]))
    a = allocate_tolerances(M, eps[:3], eps[3:], kappa, w1, w2, max_dv=ub.reshape(-1, 2))
    best, _ = brute_force(M, eps, kappa, w1, w2, ub)
    check_valid(a, M, eps, kappa, ub)
    assert a.objective == pytest.approx(best, abs=1e-9)
    assert a.relaxation_objective >= a.objective - 1e-9


@pytest.mark.parametrize("seed", range(30, 45))
def test_w2_zero_is_log_volume_optimum(seed):
    rng = np.random.default_rng(seed)
    M, eps, ub = small_instance(rng)
    a = allocate_tolerances(M, eps[:3], eps[3:], w2=0.0, max_dv=ub)
    best, X = brute_force(M, eps, 1.0, 1.0, 0.0, ub)
    assert a.objective == pytest.approx(best, abs=1e-9)
    assert a.objective == pytest.approx(np.log(2.0 * a.dv + 1.0).sum(), abs=1e-12)


@pytest.mark.parametrize("seed", range(45, 60))
def test_large_w2_raises_delta(seed):
    rng = np.random.default_rng(seed)
    M, eps, ub = small_instance(rng)
    a0 = allocate_tolerances(M, eps[:3], eps[3:], w2=0.0, max_dv=ub)
    a1 = allocate_tolerances(M, eps[:3], eps[3:], w2=1e3, max_dv=ub)
    assert a1.delta >= a0.delta
    # w2 beyond any log-volume difference: Δ is the largest feasible uniform level.
    levels = [d for d in range(int(ub.min()) + 1) if feasible(M, eps, 1.0, np.full(ub.size, d))]
    assert a1.delta == max(levels)
    best, _ = brute_force(M, eps, 1.0, 1.0, 1e3, ub)
    assert a1.objective == pytest.approx(best, abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_bound_tightening_keeps_optimum(seed, monkeypatch):
    """The reduced-cost tightening must not change the optimum (vs the plain MILP)."""
    rng = np.random.default_rng(500 + seed)
    M = random_M(rng, 5)
    eps = np.concatenate([EPS_R, EPS_T]) * 0.5
    a = allocate_tolerances(M, eps[:3], eps[3:], max_dv=12)
    monkeypatch.setattr(allocation, "_tighten", lambda A, lam, lo, hi, *args: (lo, hi))
    b = allocate_tolerances(M, eps[:3], eps[3:], max_dv=12)
    assert a.objective == pytest.approx(b.objective, abs=1e-9)


def hypograph_milp(M, eps, kappa, w1, w2, ub):
    """Independent reference: the chord (hypograph) MILP, unparameterised, zero gap."""
    n, U = M.shape[1], int(np.max(ub))
    f = np.log(2.0 * np.arange(U + 1) + 1.0)
    dv, s, delta = cp.Variable(n, integer=True), cp.Variable(n), cp.Variable()
    cons = [s <= f[k] + (f[k + 1] - f[k]) * (dv - k) for k in range(U)]
    cons += [kappa * np.abs(M) @ dv <= eps * (1 - 1e-9), dv >= delta, delta >= 0, dv <= ub]
    problem = cp.Problem(cp.Maximize(w1 * cp.sum(s) + w2 * delta), cons)
    problem.solve(solver=cp.HIGHS, mip_rel_gap=0.0, mip_abs_gap=0.0)
    x = np.rint(dv.value)
    assert feasible(M, eps, kappa, x)
    return objective(x, w1, w2)


@pytest.mark.parametrize("seed", range(6))
def test_equals_hypograph_milp(seed):
    rng = np.random.default_rng(700 + seed)
    K = 6 + seed % 3
    M = random_M(rng, K)
    ub = rng.integers(4, 13, size=2 * K)
    eps = np.abs(M) @ ub * rng.uniform(0.1, 0.5, 6)
    w2 = 5.0 if seed % 2 else 0.0
    a = allocate_tolerances(M, eps[:3], eps[3:], 1.0, 1.0, w2, max_dv=ub)
    assert a.objective == pytest.approx(hypograph_milp(M, eps, 1.0, 1.0, w2, ub), abs=1e-9)


@pytest.mark.parametrize("seed", range(10))
def test_tighten_keeps_every_good_point(seed):
    """Every feasible integer point with J >= j0 survives the reduced-cost tightening."""
    rng = np.random.default_rng(900 + seed)
    M, eps, ub = small_instance(rng, K=2 + seed % 2)
    w1, w2 = 1.0, float(rng.choice([0.0, 5.0]))
    A = np.abs(M) / eps[:, None]
    n, lo, hi = ub.size, np.zeros(ub.size), ub.astype(np.float64)
    relax = allocation._problem(n, allocation._bucket(hi.max()), "relaxation")
    allocation._solve(relax, A, lo, hi, w1, w2)
    lam = np.clip(relax.rows.dual_value, 0.0, None)
    best, X = brute_force(M, eps * (1 - 1e-9), 1.0, w1, w2, ub)
    J = w1 * np.log(2.0 * X + 1.0).sum(axis=1) + w2 * X.min(axis=1)
    shrunk = False
    for j0 in (best, best - 0.05, best - 0.3, np.quantile(J, 0.9)):
        lo_t, hi_t = allocation._tighten(A, lam, lo, hi, w1, w2, j0)
        good = X[J >= j0]
        assert np.all(good >= lo_t) and np.all(good <= hi_t)
        shrunk |= bool(np.sum(hi_t - lo_t) < np.sum(hi - lo))
    assert shrunk  # the test would notice a tightening that never tightens


def test_tighten_is_exact_when_constraint_is_slack():
    """lambda = 0 makes the bound exact: with j0 = J(ub) only x = ub survives."""
    rng = np.random.default_rng(17)
    M = random_M(rng, 3)
    ub = np.array([3, 5, 2, 6, 4, 4])
    eps = 10.0 * np.abs(M) @ ub
    A = np.abs(M) / eps[:, None]
    lo, hi = np.zeros(6), ub.astype(np.float64)
    for w2 in (0.0, 5.0):
        lo_t, hi_t = allocation._tighten(A, np.zeros(6), lo, hi, 1.0, w2, objective(ub, 1.0, w2))
        np.testing.assert_array_equal(lo_t, ub)
        np.testing.assert_array_equal(hi_t, ub)
        lo_t, hi_t = allocation._tighten(A, np.zeros(6), lo, hi, 1.0, w2, 0.0)
        np.testing.assert_array_equal(lo_t, lo)
        np.testing.assert_array_equal(hi_t, hi)


def test_deterministic_and_history_independent():
    rng = np.random.default_rng(7)
    M1, M2 = random_M(rng, 6), random_M(rng, 6)
    a = allocate_tolerances(M1, EPS_R, EPS_T, max_dv=32)
    allocate_tolerances(M2, EPS_R, EPS_T, max_dv=32)
    b = allocate_tolerances(M1, EPS_R, EPS_T, max_dv=32)
    np.testing.assert_array_equal(a.dv, b.dv)
    assert a.objective == b.objective


def test_objective_non_increasing_in_kappa():
    rng = np.random.default_rng(11)
    M = random_M(rng, 8)
    eps = np.concatenate([EPS_R, EPS_T])
    kappas = [1.0, 1.5, 2.0, 3.0]
    allocs = [allocate_tolerances(M, EPS_R, EPS_T, k, max_dv=32) for k in kappas]
    for k, a in zip(kappas, allocs, strict=True):
        check_valid(a, M, eps, k, np.full(16, 32))
        assert a.kappa == k
    for i in range(len(kappas) - 1):
        assert allocs[i + 1].objective <= allocs[i].objective + 1e-9
        # the larger kappa's allocation is feasible for every smaller kappa
        for j in range(i + 1):
            assert feasible(M, eps, kappas[j], allocs[i + 1].dv)
    assert allocs[-1].objective < allocs[0].objective


def test_zero_column_needs_max_dv():
    rng = np.random.default_rng(3)
    M = random_M(rng, 3)
    M[:, 3] = 0.0
    with pytest.raises(ValueError, match=r"^max_dv: required because keypoint coordinate 3"):
        allocate_tolerances(M, EPS_R, EPS_T)
    a = allocate_tolerances(M, EPS_R, EPS_T, max_dv=5)
    assert a.dv.ravel()[3] == 5
    ub = np.array([[4, 4], [4, 7], [4, 4]])
    b = allocate_tolerances(M, EPS_R, EPS_T, max_dv=ub)
    assert b.dv[1, 1] == 7
    assert np.all(b.dv <= ub)


def test_max_dv_none_uses_constraint_bounds():
    rng = np.random.default_rng(4)
    M = random_M(rng, 2)
    eps = np.concatenate([EPS_R, EPS_T]) * 0.05
    a = allocate_tolerances(M, eps[:3], eps[3:])
    own = np.floor(np.min(eps[:, None] / np.abs(M), axis=0))
    assert np.all(a.max_dv.ravel() <= own)
    best, _ = brute_force(M, eps, 1.0, 1.0, 5.0, own)
    assert a.objective == pytest.approx(best, abs=1e-9)


def test_max_dv_forms_agree():
    rng = np.random.default_rng(5)
    M = random_M(rng, 4)
    eps = np.concatenate([EPS_R, EPS_T])
    a = allocate_tolerances(M, eps[:3], eps[3:], max_dv=3)
    b = allocate_tolerances(M, eps[:3], eps[3:], max_dv=np.full((4, 2), 3))
    c = allocate_tolerances(M, eps[:3], eps[3:], max_dv=[3] * 8)
    assert a.objective == b.objective == c.objective
    z = allocate_tolerances(M, eps[:3], eps[3:], max_dv=0)
    assert np.all(z.dv == 0) and z.objective == 0.0


def test_tiny_column_without_max_dv_is_refused():
    M = np.vstack([np.full((3, 2), 0.05), np.full((3, 2), 0.1)])
    M[:, 1] = 1e-9
    with pytest.raises(ValueError, match=r"^max_dv: expected bounds <="):
        allocate_tolerances(M, EPS_R, EPS_T)
    a = allocate_tolerances(M, EPS_R, EPS_T, max_dv=64)
    assert a.dv[0, 1] == 64


def test_allocation_is_frozen(k23):
    _, a = k23
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.delta = 3


M_OK = np.vstack([np.full((3, 4), 0.05), np.full((3, 4), 0.1)])


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"M": np.ones((5, 4))}, "M"),
        ({"M": np.ones((6, 3))}, "M"),
        ({"M": np.ones((6, 0))}, "M"),
        ({"M": np.ones(6)}, "M"),
        ({"M": np.where(np.eye(6, 4) > 0, np.nan, M_OK)}, "M"),
        ({"M": np.where(np.eye(6, 4) > 0, np.inf, M_OK)}, "M"),
        ({"eps_r": [10.0, 0.0, 10.0]}, "eps_r"),
        ({"eps_r": [10.0, 10.0]}, "eps_r"),
        ({"eps_t": [4.0, -4.0, 20.0]}, "eps_t"),
        ({"eps_t": [4.0, np.nan, 20.0]}, "eps_t"),
        ({"kappa": 0.0}, "kappa"),
        ({"kappa": -1.0}, "kappa"),
        ({"kappa": np.inf}, "kappa"),
        ({"w1": 0.0}, "w1"),
        ({"w2": -1.0}, "w2"),
        ({"w2": np.nan}, "w2"),
        ({"max_dv": -1}, "max_dv"),
        ({"max_dv": 2.5}, "max_dv"),
        ({"max_dv": [3, 3, 3]}, "max_dv"),
        ({"max_dv": np.full((2, 2), -1)}, "max_dv"),
        ({"max_dv": True}, "max_dv"),
        ({"max_dv": "ten"}, "max_dv"),
    ],
)
def test_bad_input(kwargs, name):
    args = {"M": M_OK, "eps_r": EPS_R, "eps_t": EPS_T, "kappa": 1.0, "w1": 1.0, "w2": 5.0}
    args["max_dv"] = 8
    args.update(kwargs)
    with pytest.raises(ValueError, match=rf"^{name}:"):
        allocate_tolerances(
            args["M"],
            args["eps_r"],
            args["eps_t"],
            args["kappa"],
            args["w1"],
            args["w2"],
            max_dv=args["max_dv"],
        )


def test_allocate_many_in_processes_equals_one_by_one():
    rng = np.random.default_rng(42)
    problems = [
        (random_M(rng, 23), [10.0] * 3, [4.0, 4.0, 20.0], kappa)
        for kappa in (1.0, 1.5)
        for _ in range(10)
    ]
    pooled = allocation.allocate_many(problems, workers=2, max_dv=64)
    for (M, eps_r, eps_t, kappa), a in zip(problems, pooled):
        b = allocate_tolerances(M, eps_r, eps_t, kappa, max_dv=64)
        assert np.array_equal(a.dv, b.dv) and a.objective == b.objective and a.kappa == kappa
    with pytest.raises(ValueError, match="^workers"):
        allocation.allocate_many(problems, workers=0)
    bad = [*problems[:19], (np.full((6, 46), np.nan), [10.0] * 3, [4.0, 4.0, 20.0])]
    with pytest.raises(ValueError, match="^M"):
        allocation.allocate_many(bad, workers=2, max_dv=64)


def cell_brute_force(M, f, eps, kappa, w1, w2, below_max, above_max, every=False):
    """Best objective and its points over every integer (l, h) within the caps whose every
    pixel deviation ``p − x`` keeps ``κ |M δ| ≤ ε`` (pixels enumerated one by one); with
    ``every``, all such points."""
    n = M.shape[1]
    caps = np.concatenate([below_max, above_max])
    X = np.indices([int(c) + 1 for c in caps]).reshape(2 * n, -1).T
    best, points = -np.inf, []
    for x in X:
        lo, hi = x[:n], x[n:]
        # Largest and smallest M δ over the pixels, coordinate by coordinate.
        errors = [np.outer(M[:, j], np.arange(-lo[j], hi[j] + 1) - f[j]) for j in range(n)]
        top = sum(e.max(axis=1) for e in errors)  # (6,): each coordinate's worst pixel
        low = sum(e.min(axis=1) for e in errors)
        if np.all(kappa * np.maximum(top, -low) <= eps):
            if every:
                points.append(x)
                continue
            J = w1 * 0.5 * np.log(2.0 * x + 1.0).sum() + w2 * x.min()
            if J > best + 1e-12:
                best, points = J, [x]
            elif J > best - 1e-12:
                points.append(x)
    return best, points


@pytest.mark.parametrize("seed", range(12))
def test_cells_are_sound_maximal_and_best_among_symmetric_ones(seed):
    rng = np.random.default_rng(4100 + seed)
    K = 1
    M = random_M(rng, K)
    f = rng.uniform(-0.5, 0.5, 2 * K)
    below_max, above_max = rng.integers(0, 4, 2 * K), rng.integers(0, 4, 2 * K)
    eps = np.abs(M) @ (below_max + above_max + 1.0) * rng.uniform(0.1, 0.6, 6) + 1e-6
    kappa, w2 = float(rng.choice([1.0, 1.5])), float(rng.choice([0.0, 5.0]))
    a = allocation.allocate_cells(
        M, f.reshape(K, 2), eps[:3], eps[3:], kappa, 1.0, w2,
        max_below=below_max.reshape(K, 2), max_above=above_max.reshape(K, 2),
    )  # fmt: skip
    _, points = cell_brute_force(M, f, eps, kappa, 1.0, w2, below_max, above_max)
    if not points:  # no cell holding the nearest pixel keeps the bound
        assert not a.feasible and np.any(kappa * np.abs(M @ f) > eps * (1 - 1e-9))
        return
    assert a.feasible
    x = np.concatenate([a.below.ravel(), a.above.ravel()])
    good = {tuple(p) for p in cell_brute_force(M, f, eps, kappa, 1.0, 0.0, below_max, above_max,
                                               every=True)[1]}  # fmt: skip
    assert tuple(x) in good  # every pixel checked one by one
    for j in range(x.size):  # maximal: no cell can take one more pixel
        y = x.copy()
        y[j] += 1
        assert tuple(y) not in good or y[j] > np.r_[below_max, above_max][j]
    # It grew from the best cells symmetric about the nearest pixel: every δ whose cells
    # [c − δ, c + δ] keep the bound (pixels past the border counted) has J at most theirs.
    sym_J = []
    for d in (
        np.indices([int(max(b, c)) + 1 for b, c in zip(below_max, above_max)]).reshape(2 * K, -1).T
    ):
        top = sum(np.max(np.outer(M[:, j], np.arange(-d[j], d[j] + 1) - f[j]), axis=1)
                  for j in range(2 * K))  # fmt: skip
        low = sum(np.min(np.outer(M[:, j], np.arange(-d[j], d[j] + 1) - f[j]), axis=1)
                  for j in range(2 * K))  # fmt: skip
        if np.all(kappa * np.maximum(top, -low) <= eps * (1 - 1e-9)):
            sym_J.append(np.log(2.0 * d + 1.0).sum() + w2 * d.min())
    assert a.symmetric.objective == pytest.approx(max(sym_J), abs=1e-9)
    assert np.all(kappa * a.error <= eps)


def test_cells_of_a_centred_keypoint_are_the_paper_box():
    """With the exact keypoint on a pixel the cells are the symmetric tolerances' boxes."""
    rng = np.random.default_rng(77)
    M = random_M(rng, 3)
    box = allocate_tolerances(M, EPS_R, EPS_T, max_dv=20)
    cells = allocation.allocate_cells(
        M, np.zeros((3, 2)), EPS_R, EPS_T, max_below=np.full((3, 2), 20),
        max_above=np.full((3, 2), 20),
    )  # fmt: skip
    assert np.array_equal(cells.symmetric.dv, box.dv)  # no offset: the same problem
    assert np.all(cells.below >= box.dv) and np.all(cells.above >= box.dv)
    assert np.all(cells.error <= np.r_[EPS_R, EPS_T])


def test_cells_refuse_when_the_pixel_grid_alone_exceeds_the_tolerance():
    M = np.vstack([np.full((3, 2), 30.0), np.full((3, 2), 1.0)])  # 30° per pixel
    a = allocation.allocate_cells(
        M, [[0.4, 0.0]], EPS_R, EPS_T, max_below=[[5, 5]], max_above=[[5, 5]]
    )
    assert not a.feasible and a.symmetric is None
    assert a.error[0] == pytest.approx(12.0) and np.all(a.below == 0) and np.all(a.above == 0)
    ok = allocation.allocate_cells(
        M, [[0.3, 0.0]], EPS_R, EPS_T, max_below=[[5, 5]], max_above=[[5, 5]]
    )
    assert ok.feasible and ok.error[0] == pytest.approx(9.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(offsets=[[0.7, 0.0]]), "^offsets: expected values in"),
        (dict(offsets=[[0.0, 0.0], [0.0, 0.0]]), "^offsets: expected"),
        (dict(max_below=[[-1, 0]]), "^max_below: expected non-negative integers"),
        (dict(max_above=[[1.5, 0]]), "^max_above: expected non-negative integers"),
    ],
)
def test_cells_bad_arguments_are_named(kwargs, message):
    M = random_M(np.random.default_rng(3), 1)
    args = dict(offsets=[[0.0, 0.0]], max_below=[[2, 2]], max_above=[[2, 2]]) | kwargs
    with pytest.raises(ValueError, match=message):
        allocation.allocate_cells(M, eps_r=EPS_R, eps_t=EPS_T, **args)
