"""Optimal integer allocation of keypoint tolerances (paper §6.2, docs/design.md §4.2-4.3).

Given the sensitivity ``M = dξ/dv`` (6, 2K) and pose tolerances ``ε = [ε_r, ε_t]``, a box
of integer half-widths ``δv`` (heatmap pixels) around the keypoints keeps every pose error
within ``|δξ| ≤ ε`` to first order iff ``κ |M| δv ≤ ε`` (the 6 rows of ``κ |P_ξ M| δv ≤ b``
with ``P_ξ = [I; −I]``, ``b = [ε; ε]``). :func:`allocate_tolerances` solves exactly::

    maximise    J = w1 Σ_j log(2 δv_j + 1) + w2 Δ
    subject to  κ |M| δv ≤ ε,   0 ≤ Δ ≤ δv_j ≤ max_dv_j,   δv integer.

``2δv_j + 1`` is the number of heatmap pixels accepted on that axis, so the first term is
the log of the box's discrete volume.

Exactness. ``f(x) = log(2x + 1)`` is concave, so on integers it equals the minimum of its
chords ``f(k) + (f(k+1) − f(k)) (x − k)``, ``k = 0 … U−1`` (the hypograph formulation);
the one-hot model ``δv_j = Σ_v v y_jv``, ``Σ_v y_jv = 1``, objective ``Σ_jv f(v) y_jv``
with binary ``y`` is exact as well. Both have the same continuous relaxation (the concave
envelope of ``f``), an upper bound on ``J``. The MILP solved is the one-hot one (on K = 23
HiGHS closes the zero gap about 1.6-2x faster at the median than with the hypograph MILP,
up to 6x in the slow tail); the relaxation is solved as the chord LP (far fewer columns).
Both run in cvxpy + HiGHS at zero MIP gap, are built once per ``(2K, U)`` with parameters
(``A = κ|M|/ε`` row-wise so the constraint reads ``A δv ≤ 1``, bounds, weights) and are
cached: a call only sets values and re-solves.

Speed-up that keeps the optimum exact: the relaxation's multipliers ``λ ≥ 0`` of
``A δv ≤ 1`` give, by weak duality, for every feasible integer ``δv`` with ``min δv = d``,
``J(δv) ≤ B(d) − Σ_j loss_j(δv_j)`` with separable losses ``≥ 0``. With ``J_0`` the value
of a greedy integer point, every value of ``δv_j`` whose loss alone exceeds ``B − J_0`` is
removed from its bounds before the MILP is solved (reduced-cost bound tightening).
"""

from __future__ import annotations

import functools
import multiprocessing
import threading
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from kpstudy._checks import choice, float_array, integer, positive

__all__ = [
    "MAX_BOUND",
    "TOLERANCE_UNITS",
    "Allocation",
    "CellAllocation",
    "allocate_cells",
    "allocate_many",
    "cell_error",
    "allocate_tolerances",
    "allocation_scale",
]

#: The two readings of the allocated tolerances (docs/design.md §3). ``'heatmap'``: the
#: sensitivity is taken per heatmap pixel, so ``δv`` is in heatmap pixels, the units of
#: the cells the verifier proves (sound). ``'paper'``: the sensitivity is taken per image
#: pixel and the integer ``δv`` is then used as heatmap pixels, each ``1/scale`` image
#: pixels wide (4.6–6.3× at 64×64 heatmaps of 640×400 renders): the reading that
#: reproduces the paper's numbers, and looser than its own first-order guarantee.
TOLERANCE_UNITS = ("heatmap", "paper")

#: Largest per-coordinate bound (heatmap pixels) accepted (the model has 2K·(U+1) binaries).
MAX_BOUND = 4096
#: The solver sees ``A δv ≤ 1 − _TIGHTEN``, so the rounded integer point satisfies
#: ``κ|M|δv ≤ ε`` strictly in float64 (a point closer than 1e-9 relative to the boundary
#: is given up).
_TIGHTEN = 1e-9
_RHS = 1.0 - _TIGHTEN
#: HiGHS may restart its search only on models with more values per coordinate than this
#: (measured on 23 keypoints: without restarts the median MILP time at 64×64 heatmaps
#: falls from 0.13 to 0.08 s at α = 1; with more values restarts avoid a slow tail: on
#: 144 T-prob problems allocated per image pixel, capped at 64, the mean time falls from
#: 0.75 to 0.47 s and the worst from 6.6 to 2.3 s, while per heatmap pixel the mean stays
#: 0.10 s with this threshold).
_RESTART_ABOVE = 32
_HIGHS_OPTIONS = {
    "mip_rel_gap": 0.0,
    "mip_abs_gap": 0.0,
    "primal_feasibility_tolerance": 1e-10,
    "mip_feasibility_tolerance": 1e-10,
    # Search settings only (the optimum stays exact). The greedy point already gives a
    # close incumbent; sub-MIP heuristics (RINS, RENS) cost more than they save here.
    # Restarts help only on the large models (values up to 256, the ResNet's heatmaps):
    # see _RESTART_ABOVE. Feasibility jump and symmetry detection find nothing on these
    # models; without them the median falls 2-19 % (50 images, α = 0.5-2, 64 and 256).
    "mip_heuristic_effort": 0.0,
    "mip_heuristic_run_rins": False,
    "mip_heuristic_run_rens": False,
    "mip_heuristic_run_feasibility_jump": False,
    "mip_detect_symmetry": False,
}


@dataclass(frozen=True)
class Allocation:
    """An optimal integer tolerance allocation.

    Attributes
    ----------
    dv : ndarray, shape (K, 2), int64
        Tolerated half-widths ``[du, dv]`` per keypoint, heatmap pixels.
    delta : int
        ``Δ = min(dv)``.
    objective : float
        ``J = w1 Σ log(2 dv + 1) + w2 Δ`` at ``dv`` (the integer optimum).
    relaxation_objective : float
        Optimum of the continuous relaxation (integrality dropped), an upper bound on ``J``.
    relaxation_dv : ndarray, shape (K, 2), float64
        The relaxation's maximiser, heatmap pixels.
    status : str
        The MILP solver's status (``"optimal"``).
    kappa : float
        Scaling factor of the constraint ``κ |M| dv ≤ ε``.
    eps_r : ndarray, shape (3,)
        Rotation tolerances, degrees.
    eps_t : ndarray, shape (3,)
        Translation tolerances, metres.
    max_dv : ndarray, shape (K, 2), int64
        Upper bounds used: the given ``max_dv`` capped by the constraint alone.
    """

    dv: np.ndarray
    delta: int
    objective: float
    relaxation_objective: float
    relaxation_dv: np.ndarray = field(repr=False)
    status: str
    kappa: float
    eps_r: np.ndarray
    eps_t: np.ndarray
    max_dv: np.ndarray = field(repr=False)

    def __str__(self) -> str:
        return (
            f"Allocation(K={self.dv.shape[0]}, kappa={self.kappa:g}, delta={self.delta}, "
            f"du in [{self.dv[:, 0].min()}, {self.dv[:, 0].max()}], "
            f"dv in [{self.dv[:, 1].min()}, {self.dv[:, 1].max()}], "
            f"J={self.objective:.6g} (relaxation {self.relaxation_objective:.6g}), "
            f"status={self.status})"
        )


def allocate_tolerances(
    M,
    eps_r,
    eps_t,
    kappa: float = 1.0,
    w1: float = 1.0,
    w2: float = 5.0,
    *,
    max_dv=None,
) -> Allocation:
    """Largest integer keypoint tolerances that keep the linearised pose error within ``ε``.

    Parameters
    ----------
    M : array_like, shape (6, 2K)
        Sensitivity ``dξ/dv``: rows ``[roll, pitch, yaw]`` in degrees per pixel and
        ``[tx, ty, tz]`` in metres per pixel; columns ``[u1, v1, u2, v2, …]`` in heatmap
        pixels. K ≥ 1, finite.
    eps_r : array_like, shape (3,)
        Rotation tolerances (roll, pitch, yaw), degrees, > 0.
    eps_t : array_like, shape (3,)
        Translation tolerances (tx, ty, tz), metres, > 0.
    kappa : float
        Scaling factor ``κ > 0`` of the constraint ``κ |M| δv ≤ ε``.
    w1 : float
        Weight ``> 0`` of the log-volume term ``Σ log(2 δv_j + 1)``.
    w2 : float
        Weight ``≥ 0`` of the smallest half-width ``Δ = min δv``.
    max_dv : int or array_like of int, shape (K, 2) or (2K,), optional
        Upper bounds on ``δv`` in heatmap pixels (≥ 0), e.g. the heatmap size. If None, each
        coordinate is bounded by the constraint alone, ``floor(min_i ε_i / (κ |M|_ij))``,
        which needs every column of ``M`` to be non-zero. The bounds actually used (also
        capped by the constraint) must be ≤ :data:`MAX_BOUND`.

    Returns
    -------
    Allocation
        ``dv`` (K, 2) int64, an exact integer optimum; ``κ |M| dv ≤ ε`` holds in float64.

    Raises
    ------
    ValueError
        On a bad argument; the message starts with the argument's name.
    RuntimeError
        If the solver fails or its rounded point is infeasible or not optimal.

    Examples
    --------
    >>> M = np.vstack([np.full((3, 2), 0.05), [[0.1, 0.3], [0.1, 0.3], [0.1, 0.3]]])
    >>> allocate_tolerances(M, [10, 10, 10], [4, 4, 20], max_dv=64).dv
    array([[12,  9]])
    """
    M = float_array(M, "M", (6, None))
    if M.shape[1] < 2 or M.shape[1] % 2:
        raise ValueError(f"M: expected shape (6, 2K) with K >= 1, got {M.shape}")
    n = M.shape[1]
    K = n // 2
    eps = np.concatenate([positive(eps_r, "eps_r", (3,)), positive(eps_t, "eps_t", (3,))])
    kappa = float(positive(kappa, "kappa"))
    w1 = float(positive(w1, "w1"))
    w2 = float(float_array(w2, "w2", ()))
    if w2 < 0:
        raise ValueError(f"w2: expected a value >= 0, got {w2}")

    A = kappa * np.abs(M) / eps[:, None]  # constraint A δv ≤ 1
    ub = _bounds(A, max_dv, K)
    lo = np.zeros(n)

    # Continuous relaxation: upper bound, multipliers for the tightening.
    relax = _problem(n, _bucket(ub.max()), "relaxation")
    with _LOCK:
        x_rel, status_rel = _solve(relax, A, lo, ub, w1, w2)
        relaxation_objective = float(relax.problem.value) if x_rel is not None else np.nan
        lam = relax.rows.dual_value
    if x_rel is None:
        raise RuntimeError(f"allocate_tolerances: the relaxation's status is {status_rel!r}")
    lam = np.zeros(6) if lam is None else np.clip(np.asarray(lam, dtype=np.float64), 0, None)

    # Greedy integer point, then drop the values the Lagrangian bound rules out.
    x0 = _greedy(A, lo, ub, x_rel, w1, w2)
    j0 = _objective(x0, w1, w2)
    lo_t, hi_t = _tighten(A, lam, lo, ub, w1, w2, j0)
    if not np.all((lo_t <= x0) & (x0 <= hi_t)):  # numerically inconsistent: no tightening
        lo_t, hi_t = lo, ub

    U = _bucket(hi_t.max())
    milp = _problem(n, U, "milp")
    with _LOCK:
        x_int, status = _solve(milp, A, lo_t, hi_t, w1, w2, restart=U > _RESTART_ABOVE)
    if x_int is None or status != cp.OPTIMAL:
        raise RuntimeError(f"allocate_tolerances: the MILP's status is {status!r}")

    dv = np.rint(x_int).astype(np.int64)
    lhs = kappa * np.abs(M) @ dv
    if not (np.all(lhs <= eps) and np.all(dv >= 0) and np.all(dv <= ub)):
        raise RuntimeError(
            "allocate_tolerances: the solver's rounded point is infeasible "
            f"(kappa*|M|@dv / eps = {(lhs / eps).tolist()}, dv = {dv.tolist()})"
        )
    objective = _objective(dv, w1, w2)
    if objective < j0 - 1e-9 * max(1.0, abs(j0)):
        raise RuntimeError(
            f"allocate_tolerances: the MILP returned J = {objective!r}, below the greedy "
            f"point's J = {j0!r}"
        )
    return Allocation(
        dv=dv.reshape(K, 2),
        delta=int(dv.min()),
        objective=objective,
        relaxation_objective=relaxation_objective,
        relaxation_dv=np.clip(x_rel, 0.0, None).reshape(K, 2),
        status=status,
        kappa=kappa,
        eps_r=eps[:3].copy(),
        eps_t=eps[3:].copy(),
        max_dv=ub.astype(np.int64).reshape(K, 2),
    )


@dataclass(frozen=True)
class CellAllocation:
    """Integer pixel ranges around the exact keypoints (the sound reading).

    On each axis a keypoint's cell is ``[c − below, c + above]`` with ``c`` the pixel
    nearest the exact keypoint ``c + offset``. Every pixel of every cell keeps the
    first-order pose error, measured from the exact keypoints, within ``ε / κ``.

    Attributes
    ----------
    below, above : ndarray, shape (K, 2), int64
        Pixels the cell reaches below and above ``c`` per axis ``[u, v]``, heatmap pixels
        (zeros when not ``feasible``).
    feasible : bool
        False when the nearest pixels alone already exceed ``ε / κ`` to first order: no
        cell certifies the instance at this heatmap resolution.
    offsets : ndarray, shape (K, 2), float64
        Exact keypoint minus ``c``, heatmap pixels, in ``[−0.5, 0.5]``.
    error : ndarray, shape (6,), float64
        Largest first-order pose error ``|M δ|`` over every pixel of every cell (over the
        nearest pixels alone when not feasible), degrees and metres; ``κ · error ≤ ε``
        iff ``feasible``.
    delta : int
        ``Δ = min(below, above)``.
    objective : float
        ``J = w1 Σ log(below + above + 1) + w2 Δ`` (the log of the cells' discrete
        volume, as :func:`allocate_tolerances`'s; NaN when not feasible).
    symmetric : Allocation or None
        The exact optimum over cells symmetric about ``c`` that the ranges grow from.
    kappa : float
    eps_r, eps_t : ndarray, shape (3,)
    """

    below: np.ndarray
    above: np.ndarray
    feasible: bool
    offsets: np.ndarray
    error: np.ndarray
    delta: int
    objective: float
    symmetric: Allocation | None
    kappa: float
    eps_r: np.ndarray
    eps_t: np.ndarray


def allocate_cells(
    M,
    offsets,
    eps_r,
    eps_t,
    kappa: float = 1.0,
    w1: float = 1.0,
    w2: float = 5.0,
    *,
    max_below,
    max_above,
) -> CellAllocation:
    """Integer pixel ranges whose every pixel keeps the linearised pose error, measured
    from the *exact* keypoints, within ``ε / κ``.

    With ``f`` the offsets of the exact keypoints from their nearest pixels ``c``, a cell
    ``[c − δ, c + δ]`` symmetric about ``c`` has its largest first-order error over its
    pixels at ``|M| δ + |M f|`` (row by row), so the best symmetric cells are exactly
    :func:`allocate_tolerances` with ``ε − κ |M f|`` in place of ``ε``; where that is ≤ 0
    on some row the nearest pixels alone exceed the tolerance and no cell can keep it
    (``feasible`` False). The cells are then clipped to the heatmap and grown one pixel at
    a time on the side that keeps every pixel within ``ε / κ`` (:func:`cell_error`), the
    smallest cell first: the rounding offsets leave room on one side.

    The exact optimum over every asymmetric range, a MILP in ``4K`` integers with the
    offsets in its right-hand sides, is one to two orders of magnitude slower for a ``J``
    up to a few units larger (docs/design.md §4.4).

    Parameters
    ----------
    M : array_like, shape (6, 2K)
        Sensitivity ``dξ/dv`` per heatmap pixel (as :func:`allocate_tolerances`).
    offsets : array_like, shape (K, 2)
        Exact keypoint minus its nearest pixel ``(u, v)``, heatmap pixels, each in
        ``[−0.5, 0.5]``.
    eps_r, eps_t, kappa, w1, w2 :
        As :func:`allocate_tolerances`.
    max_below, max_above : array_like of int, shape (K, 2)
        Pixels between the nearest pixel and the heatmap's first and last pixel per axis
        (≥ 0): a cell ends at the border.

    Returns
    -------
    CellAllocation
        ``feasible`` False (and zero ranges) where no cell keeps ``ε / κ``.

    Examples
    --------
    >>> M = np.vstack([np.full((3, 2), 0.05), [[0.1, 0.3], [0.1, 0.3], [0.1, 0.3]]])
    >>> a = allocate_cells(M, [[0.0, 0.0]], [10, 10, 10], [4, 4, 20],
    ...                    max_below=[[64, 64]], max_above=[[64, 64]])
    >>> a.below.tolist(), a.above.tolist()
    ([[12, 9]], [[12, 9]])
    >>> b = allocate_cells(M, [[0.0, 0.4]], [10, 10, 10], [4, 4, 20],
    ...                    max_below=[[64, 64]], max_above=[[64, 64]])
    >>> b.below.tolist(), b.above.tolist(), bool(np.all(b.error <= [10, 10, 10, 4, 4, 20]))
    ([[11, 9]], [[11, 10]], True)
    """
    M = float_array(M, "M", (6, None))
    if M.shape[1] < 2 or M.shape[1] % 2:
        raise ValueError(f"M: expected shape (6, 2K) with K >= 1, got {M.shape}")
    K = M.shape[1] // 2
    f = float_array(offsets, "offsets", (K, 2))
    if np.any(np.abs(f) > 0.5 + 1e-9):
        raise ValueError(f"offsets: expected values in [-0.5, 0.5], got {f.tolist()}")
    eps = np.concatenate([positive(eps_r, "eps_r", (3,)), positive(eps_t, "eps_t", (3,))])
    kappa = float(positive(kappa, "kappa"))
    caps = []
    for name, cap in (("max_below", max_below), ("max_above", max_above)):
        c = float_array(cap, name, (K, 2))
        if not np.all((c >= 0) & (c == np.rint(c))):
            raise ValueError(f"{name}: expected non-negative integers, got {c.tolist()}")
        caps.append(c.reshape(-1).astype(np.int64))
    f = f.reshape(-1)
    grid = kappa * np.abs(M @ f)  # the nearest pixels' own error, scaled by κ
    room = (eps - grid) * _RHS
    common = dict(offsets=f.reshape(K, 2), kappa=kappa, eps_r=eps[:3].copy(), eps_t=eps[3:].copy())
    if not np.all(room > 0):
        zero = np.zeros((K, 2), dtype=np.int64)
        return CellAllocation(
            below=zero, above=zero.copy(), feasible=False, error=grid / kappa, delta=0,
            objective=np.nan, symmetric=None, **common,
        )  # fmt: skip
    symmetric = allocate_tolerances(
        M, room[:3], room[3:], kappa, w1, w2, max_dv=np.maximum(*caps).reshape(K, 2)
    )
    dv = symmetric.dv.reshape(-1)
    below, above = np.minimum(dv, caps[0]), np.minimum(dv, caps[1])
    below, above = _grow(M, f, eps / kappa, below, above, caps)
    error = cell_error(M, f, below, above)
    if not np.all(kappa * error <= eps):
        raise RuntimeError(
            f"allocate_cells: cells beyond the tolerance (kappa*error / eps = "
            f"{(kappa * error / eps).tolist()})"
        )
    x = np.concatenate([below, above])
    objective = float(w1 * np.sum(np.log(below + above + 1.0)) + w2 * x.min())
    return CellAllocation(
        below=below.reshape(K, 2), above=above.reshape(K, 2), feasible=True, error=error,
        delta=int(x.min()), objective=objective, symmetric=symmetric, **common,
    )  # fmt: skip


def _grow(M, f, bound, below, above, caps) -> tuple[np.ndarray, np.ndarray]:
    """Add pixels to the cells one at a time while every pixel keeps ``|M δ| ≤ bound``
    (6,): each round the smallest cell that can grow, on its lower side first."""
    below, above = below.copy(), above.copy()
    limit = bound * _RHS
    while True:
        size = below + above
        grown = False
        for j in np.argsort(size, kind="stable"):
            for side, cap in ((below, caps[0]), (above, caps[1])):
                if side[j] >= cap[j]:
                    continue
                side[j] += 1
                if np.all(cell_error(M, f, below, above) <= limit):
                    grown = True
                    break
                side[j] -= 1
            if grown:
                break
        if not grown:
            return below, above


def cell_error(M, offsets, below, above) -> np.ndarray:
    """Largest first-order pose error ``max |M δ|`` (6,) over every pixel deviation ``δ``
    of the cells ``[−below, above]`` around the nearest pixels, measured from the exact
    keypoints (``offsets`` from the nearest pixels); all of shape (2K,) or (K, 2).

    The maximum of a linear function over the box of deviations is at a corner, per row
    ``Σ_j max(M_ij a_j, M_ij b_j)`` with ``a = −below − f``, ``b = above − f`` (and the
    same with min for the most negative error).

    Examples
    --------
    >>> M = np.array([[1.0, -2.0]] * 6)
    >>> float(cell_error(M, [0.25, 0.0], [1, 0], [0, 1])[0])  # δ ∈ [-1.25, -0.25] × [0, 1]
    3.25
    """
    M = np.asarray(M, dtype=np.float64)
    f = np.asarray(offsets, dtype=np.float64).reshape(-1)
    a = -np.asarray(below, dtype=np.float64).reshape(-1) - f
    b = np.asarray(above, dtype=np.float64).reshape(-1) - f
    hi = np.maximum(M * a, M * b).sum(axis=1)
    lo = np.minimum(M * a, M * b).sum(axis=1)
    return np.maximum(hi, -lo)


def allocation_scale(tolerance_units: str, scale):
    """The resize factors ``(sx, sy)`` (image → heatmap) the sensitivity of the allocation
    is computed with under ``tolerance_units`` (:data:`TOLERANCE_UNITS`): ``scale`` for
    ``'heatmap'``, None (image pixels) for ``'paper'``."""
    choice(tolerance_units, "tolerance_units", TOLERANCE_UNITS)
    return scale if tolerance_units == "heatmap" else None


def allocate_many(problems, *, workers: int = 1, **options) -> list[Allocation]:
    """:func:`allocate_tolerances` for many problems, in ``workers`` processes.

    Parameters
    ----------
    problems : iterable of tuples
        ``(M, eps_r, eps_t)`` or ``(M, eps_r, eps_t, kappa)`` each, as for
        :func:`allocate_tolerances`.
    workers : int
        Processes (``spawn``, started once for the batch); HiGHS solves one model at a
        time per process, so on a large batch the time per allocation falls about as
        ``1 / workers``. Batches smaller than ``8 · workers`` run in this process.
    **options :
        ``w1``, ``w2``, ``max_dv`` (and ``kappa`` when the tuples have none).

    Returns
    -------
    list of Allocation
        In the order of ``problems``; each is the exact optimum, whatever ``workers`` is.
    """
    integer(workers, "workers", minimum=1)
    problems = [tuple(p) for p in problems]
    task = functools.partial(_allocate_one, options=options)
    if workers == 1 or len(problems) < 8 * workers:
        return [task(p) for p in problems]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        return list(pool.map(task, problems, chunksize=max(1, len(problems) // (8 * workers))))


def _allocate_one(problem: tuple, options: dict) -> Allocation:
    return allocate_tolerances(*problem, **options)


def _objective(x: np.ndarray, w1: float, w2: float) -> float:
    """``J(x) = w1 Σ log(2x + 1) + w2 min x`` for an integer vector ``x``."""
    return float(w1 * np.sum(np.log(2.0 * x + 1.0)) + w2 * np.min(x))


def _bounds(A: np.ndarray, max_dv, K: int) -> np.ndarray:
    """Per-coordinate upper bounds (2K,) float: ``max_dv`` capped by ``A δv ≤ 1``."""
    n = 2 * K
    with np.errstate(divide="ignore"):
        # Slightly generous (a superset is harmless: the constraint itself stays).
        own = np.floor(np.min(_RHS / A, axis=0) * (1.0 + 1e-12))  # inf for a zero column
    if max_dv is None:
        zero = np.flatnonzero(~np.isfinite(own))
        if zero.size:
            j = int(zero[0])
            raise ValueError(
                f"max_dv: required because keypoint coordinate {j} (keypoint {j // 2}, "
                f"{'uv'[j % 2]}) does not affect the pose (column {j} of M is zero)"
            )
        bound = own
    else:
        if isinstance(max_dv, bool) or np.asarray(max_dv).dtype == bool:
            raise ValueError("max_dv: expected non-negative integers, got bool")
        m = float_array(max_dv, "max_dv", np.shape(max_dv))
        if m.shape not in ((), (K, 2), (n,)):
            raise ValueError(f"max_dv: expected an int or shape ({K}, 2) or ({n},), got {m.shape}")
        if not np.all((m >= 0) & (m == np.rint(m))):
            raise ValueError(f"max_dv: expected non-negative integers, got {m.tolist()}")
        bound = np.minimum(np.broadcast_to(m.reshape(-1), (n,)), own)
    if bound.max() > MAX_BOUND:
        j = int(np.argmax(bound))
        raise ValueError(
            f"max_dv: expected bounds <= {MAX_BOUND} pixels; coordinate {j} is bounded only "
            f"by {bound[j]:g} (pass max_dv, e.g. the heatmap size)"
        )
    return bound


def _bucket(u: float) -> int:
    """Model size ``U`` for bounds ≤ ``u``: the next power of two (≥ 1), to share cached models."""
    u = int(u)
    return 1 << (u - 1).bit_length() if u > 1 else 1


# --- cached parameterised problems -------------------------------------------------------


@dataclass
class _Problem:
    problem: cp.Problem
    A: cp.Parameter
    lo: cp.Parameter
    hi: cp.Parameter
    w1: cp.Parameter
    w2: cp.Parameter
    dv: cp.Expression  # δv (the relaxation's variable, or y @ [0, 1, …, U])
    rows: cp.Constraint  # A δv ≤ 1 − _TIGHTEN (its dual gives λ)


_CACHE: dict[tuple[int, int, str], _Problem] = {}
_LOCK = threading.Lock()  # parameters are shared state: one solve at a time per process


def _problem(n: int, U: int, kind: str) -> _Problem:
    """The cached model for ``2K = n`` coordinates with values 0 … U.

    ``kind`` is ``"milp"`` (one-hot, binary) or ``"relaxation"`` (chords, continuous).
    """
    key = (n, U, kind)
    with _LOCK:
        if key not in _CACHE:
            _CACHE[key] = _build_milp(n, U) if kind == "milp" else _build_relaxation(n, U)
        return _CACHE[key]


def _parameters(n: int) -> tuple[cp.Parameter, ...]:
    """A (6, n), lo (n,), hi (n,), w1, w2."""
    return (
        cp.Parameter((6, n), nonneg=True),
        cp.Parameter(n, nonneg=True),
        cp.Parameter(n, nonneg=True),
        cp.Parameter(nonneg=True),
        cp.Parameter(nonneg=True),
    )


def _build_milp(n: int, U: int) -> _Problem:
    """One-hot MILP (DPP): binary ``y[j, v] = 1`` iff ``δv_j = v``, ``v = 0 … U``."""
    A, lo, hi, w1, w2 = _parameters(n)
    y = cp.Variable((n, U + 1), boolean=True)
    Delta = cp.Variable()
    values = np.arange(U + 1, dtype=np.float64)
    dv = y @ values
    rows = A @ dv <= _RHS
    constraints = [cp.sum(y, axis=1) == 1, rows, dv >= lo, dv <= hi, dv >= Delta, Delta >= 0]
    objective = w1 * cp.sum(y @ np.log(2.0 * values + 1.0)) + w2 * Delta
    return _Problem(cp.Problem(cp.Maximize(objective), constraints), A, lo, hi, w1, w2, dv, rows)


def _build_relaxation(n: int, U: int) -> _Problem:
    """Chord (hypograph) LP (DPP): ``s_j ≤ f(k) + (f(k+1) − f(k)) (δv_j − k)``, k < U.

    The same value as the one-hot LP relaxation (both are the concave envelope of ``f`` on
    the integers) but with ``2K + 2`` columns, which HiGHS solves much faster.
    """
    A, lo, hi, w1, w2 = _parameters(n)
    dv = cp.Variable(n)
    s = cp.Variable(n)
    Delta = cp.Variable()
    k = np.arange(U, dtype=np.float64)
    f = np.log(2.0 * np.arange(U + 1) + 1.0)
    d = np.diff(f)
    E = sp.kron(sp.eye(n), np.ones((U, 1)), format="csr")  # (nU, n): s_j repeated U times
    D = sp.kron(sp.eye(n), d[:, None], format="csr")  # (nU, n): d_k in row (j, k)
    rows = A @ dv <= _RHS
    constraints = [E @ s - D @ dv <= np.tile(f[:-1] - d * k, n), rows, dv >= lo, dv <= hi]
    constraints += [dv >= Delta, Delta >= 0]
    objective = w1 * cp.sum(s) + w2 * Delta
    return _Problem(cp.Problem(cp.Maximize(objective), constraints), A, lo, hi, w1, w2, dv, rows)


def _solve(p: _Problem, A, lo, hi, w1, w2, restart=True) -> tuple[np.ndarray | None, str]:
    """Set the parameters and solve with HiGHS (caller holds ``_LOCK``): (δv or None, status)."""
    p.A.value = A
    p.lo.value = lo
    p.hi.value = hi
    p.w1.value = w1
    p.w2.value = w2
    try:
        # warm_start=False: the result must not depend on earlier calls.
        p.problem.solve(
            solver=cp.HIGHS, warm_start=False, mip_allow_restart=restart, **_HIGHS_OPTIONS
        )
    except cp.error.SolverError as exc:
        raise RuntimeError(f"allocate_tolerances: HiGHS failed: {exc}") from exc
    x = p.dv.value
    return (None if x is None else np.array(x, dtype=np.float64)), p.problem.status


# --- exactness-preserving speed-up: greedy point + Lagrangian bound tightening -----------


def _greedy(A, lo, hi, x_rel, w1, w2, passes: int = 5) -> np.ndarray:
    """A feasible integer point (2K,) near the relaxation: round down, fill, local search.

    Only its objective matters (a lower bound for :func:`_tighten`); the MILP decides.
    """
    best, best_j = lo.copy(), _objective(lo, w1, w2)  # lo = 0 is feasible
    d_rel = float(np.min(x_rel))
    for d in sorted({0, int(np.floor(d_rel + 1e-9)), int(np.ceil(d_rel - 1e-9))}):
        lod = np.maximum(lo, d)
        if np.any(lod > hi) or np.any(A @ lod > _RHS):
            continue
        x = np.clip(np.floor(x_rel + 1e-9), lod, hi)
        if np.any(A @ x > _RHS):
            x = lod.copy()
        x = _fill(x, A, lod, hi, w1, w2)
        jx = _objective(x, w1, w2)
        for _ in range(passes):  # move one unit from a coordinate, refill the others
            improved = False
            for i in np.flatnonzero(x > lod):
                y = x.copy()
                y[i] -= 1
                y = _fill(y, A, lod, hi, w1, w2, frozen=i)
                jy = _objective(y, w1, w2)
                if jy > jx + 1e-12:
                    x, jx, improved = y, jy, True
            if not improved:
                break
        if jx > best_j:
            best, best_j = x, jx
    return best


def _fill(x, A, lo, hi, w1, w2, frozen=None) -> np.ndarray:
    """Add units while feasible, best gain per used share of the tightest slack first."""
    x = x.copy()
    while True:
        slack = _RHS - A @ x
        ok = (x < hi) & np.all(A <= slack[:, None], axis=0)
        if frozen is not None:
            ok[frozen] = False
        if not ok.any():
            return x
        gain = w1 * (np.log(2.0 * x + 3.0) - np.log(2.0 * x + 1.0))
        is_min = x == x.min()
        if is_min.sum() == 1:
            gain = gain + w2 * is_min
        use = np.max(A / np.maximum(slack[:, None], 1e-300), axis=0)
        score = np.where(ok, gain / np.maximum(use, 1e-300), -np.inf)
        x[int(np.argmax(score))] += 1


def _tighten(A, lam, lo, hi, w1, w2, j0) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (lo, hi) that keep every feasible integer point with ``J ≥ j0``.

    For λ ≥ 0 and a feasible integer x with min x = d (weak duality):
    ``J(x) ≤ λ·1 + w2 d + Σ_j g_j(x_j)`` with ``g_j(v) = w1 f(v) − (Aᵀλ)_j v``,
    ``≤ B(d) − (G_j(d) − g_j(x_j))`` for each j, where ``G_j(d) = max_{v ≥ d} g_j(v)`` and
    ``B(d) = λ·1 + w2 d + Σ_j G_j(d)``. A value v of x_j is kept iff some d ≤ v gives
    ``B(d) − G_j(d) + g_j(v) ≥ j0`` (minus a float margin).
    """
    U = int(hi.max())
    v = np.arange(U + 1, dtype=np.float64)
    inside = (v >= lo[:, None]) & (v <= hi[:, None])
    g = np.where(inside, w1 * np.log(2.0 * v + 1.0) - (A.T @ lam)[:, None] * v, -np.inf)
    G = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]  # max over v' ≥ d
    finite = np.all(np.isfinite(G), axis=0)  # d ≤ every hi_j
    B = np.where(finite, lam.sum() * _RHS + w2 * v + np.where(finite, G, 0.0).sum(axis=0), -np.inf)
    H = np.where(finite, B - np.where(finite, G, 0.0), -np.inf)  # (n, d)
    H = np.maximum.accumulate(H, axis=1)  # best d ≤ v
    margin = 1e-9 * max(1.0, abs(j0))
    keep = inside & (H + g >= j0 - margin)
    has = keep.any(axis=1)
    first = np.argmax(keep, axis=1).astype(np.float64)
    last = (U - np.argmax(keep[:, ::-1], axis=1)).astype(np.float64)
    return np.where(has, first, lo), np.where(has, last, hi)
