"""The allocation figures of paper §8: F-alloc (``fig:deviation``) and F-kps (``fig:kps``).

* **F-alloc** — the optimal integer tolerances ``δv*`` (heatmap pixels) allocated per
  keypoint, mean ± std over images, horizontal (δu) and vertical (δv) panels, one series per
  tolerance factor α (ε = α·[10°, 10°, 10°, 4, 4, 20 m], docs/design.md §3, §4.3).
* **F-kps** — for one image, keypoint deviations caused by pose errors drawn uniformly in
  ``Ξ = {|δξ| ≤ ε}`` (the completeness samples of docs/design.md §4.9) against the allocated
  box ``[−δu, δu] × [−δv, δv]`` of a few keypoints.

Data and plotting are separate: :func:`allocation_frame` and
:func:`keypoint_deviation_samples` return arrays a test can check, :func:`plot_allocation`
and :func:`plot_keypoint_samples` only draw them. The figures are plain
:class:`matplotlib.figure.Figure` objects, not registered with pyplot, so they need no
interactive backend and no ``plt.close``; save them with ``fig.savefig(path)``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from kpstudy import _checks
from kpstudy.models.preprocess import scale_factors
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import euler_from_matrix, matrix_from_euler, project_batch, tolerance
from kpstudy.pose.pnp import solve_pnp
from kpstudy.pose.sensitivity import pose_sensitivity

__all__ = [
    "ALPHAS",
    "FRAME_COLUMNS",
    "allocation_errorbars",
    "allocation_frame",
    "allocation_table",
    "inside_fractions",
    "keypoint_deviation_samples",
    "plot_allocation",
    "plot_keypoint_samples",
]

#: Tolerance factors α of F-alloc (paper §8.3, Fig. 9).
ALPHAS = (0.5, 1.0, 1.5, 2.0)
#: Columns of :func:`allocation_frame`.
FRAME_COLUMNS = ("image", "alpha", "kappa", "keypoint", "du", "dv")


def allocation_frame(
    points_3d,
    keypoints,
    K,
    image_size,
    heatmap_size,
    alphas=ALPHAS,
    kappa: float = 1.0,
    w1: float = 1.0,
    w2: float = 5.0,
) -> pd.DataFrame:
    """Optimal integer tolerances per image, α and keypoint (the data of F-alloc).

    For each image the nominal pose is PnP on its ground-truth keypoints, the sensitivity
    ``M = dξ/dv`` is taken there in heatmap pixels, and
    :func:`~kpstudy.pose.allocation.allocate_tolerances` is solved for
    ``ε = α·[EPS_R, EPS_T]`` with ``δv`` capped by the heatmap size.

    Parameters
    ----------
    points_3d : array_like, shape (K, 3)
        Object keypoints, metres.
    keypoints : array_like, shape (N, K, 2)
        Ground-truth keypoints of N images, image pixels.
    K : array_like, shape (3, 3) or (N, 3, 3)
        Intrinsics, shared or per image.
    image_size : (int, int)
        ``(W, H)`` of the images, pixels.
    heatmap_size : int or (int, int)
        Heatmap (= model input) size, ``s`` or ``(w, h)``, pixels.
    alphas : sequence of float
        Tolerance factors α > 0.
    kappa : float
        Scaling factor κ > 0 of the allocation constraint.
    w1, w2 : float
        Allocation weights (see :func:`kpstudy.pose.allocation.allocate_tolerances`).

    Returns
    -------
    pandas.DataFrame
        Long format, ``N · len(alphas) · K`` rows ordered by (image, alpha, keypoint), with
        columns ``image`` (index), ``alpha``, ``kappa``, ``keypoint`` (0-based index),
        ``du``, ``dv`` (allocated half-widths, int, heatmap pixels).

    Raises
    ------
    ValueError
        On a bad argument (the message starts with its name) or a degenerate PnP problem.

    Examples
    --------
    >>> df = allocation_frame(P, V, K, (640, 400), 64)  # doctest: +SKIP
    >>> df.groupby(["alpha", "keypoint"])[["du", "dv"]].mean()  # doctest: +SKIP
    """
    P = _checks.float_array(points_3d, "points_3d", (None, 3))
    V = _checks.float_array(keypoints, "keypoints", (None, P.shape[0], 2))
    n_images, n_kp = V.shape[:2]
    if n_images < 1:
        raise ValueError("keypoints: expected at least one image, got shape (0, ...)")
    Ks = _intrinsics_per_image(K, n_images)
    alphas = _checks.positive(alphas, "alphas", (None,))
    if alphas.size < 1:
        raise ValueError("alphas: expected at least one tolerance factor")
    kappa = float(_checks.positive(kappa, "kappa"))
    scale, hw = _scale(image_size, heatmap_size)
    max_dv = np.tile(hw, (n_kp, 1))  # (K, 2): heatmap width for u, height for v

    blocks = []
    for i in range(n_images):
        R, t = solve_pnp(P, V[i], Ks[i])
        M = pose_sensitivity(P, V[i], Ks[i], R, t, scale=scale)
        for alpha in alphas:
            eps_r, eps_t = np.split(tolerance(alpha), 2)
            a = allocate_tolerances(M, eps_r, eps_t, kappa=kappa, w1=w1, w2=w2, max_dv=max_dv)
            blocks.append((i, alpha, a.dv))
    return pd.DataFrame(
        {
            "image": np.repeat([b[0] for b in blocks], n_kp),
            "alpha": np.repeat([b[1] for b in blocks], n_kp),
            "kappa": kappa,
            "keypoint": np.tile(np.arange(n_kp), len(blocks)),
            "du": np.concatenate([b[2][:, 0] for b in blocks]),
            "dv": np.concatenate([b[2][:, 1] for b in blocks]),
        },
        columns=list(FRAME_COLUMNS),
    )


def allocation_table(frame: pd.DataFrame, keypoint_names) -> pd.DataFrame:
    """The F-alloc table: mean and standard deviation of ``δu``, ``δv`` (heatmap pixels)
    over the images of :func:`allocation_frame`'s ``frame``, per α and keypoint, with the
    keypoint's name from ``keypoint_names`` (indexed by keypoint)."""
    table = frame.groupby(["alpha", "keypoint"])[["du", "dv"]].agg(["mean", "std"]).reset_index()
    table.columns = ["alpha", "keypoint", "du_mean", "du_std", "dv_mean", "dv_std"]
    table.insert(2, "name", [keypoint_names[k] for k in table["keypoint"]])
    return table


def plot_allocation(frame: pd.DataFrame, keypoint_names=None) -> Figure:
    """F-alloc: allocated tolerance per keypoint, mean ± std over images, per α.

    Parameters
    ----------
    frame : pandas.DataFrame
        Output of :func:`allocation_frame` with a single κ.
    keypoint_names : sequence of str, optional
        Tick labels, one per keypoint index ``0 … K−1``; default the indices.

    Returns
    -------
    matplotlib.figure.Figure
        Two panels, horizontal ``δu`` (top) and vertical ``δv`` (bottom), sharing the
        keypoint axis: per keypoint one errorbar marker per α, offset side by side, and a
        legend. The marker is the mean over images; the bar spans mean ± std, its lower
        end clipped at 0 (tolerances are never negative).
    """
    if not isinstance(frame, pd.DataFrame):
        raise ValueError(f"frame: expected a pandas DataFrame, got {type(frame).__name__}")
    missing = set(FRAME_COLUMNS) - set(frame.columns)
    if missing or frame.empty:
        raise ValueError(
            f"frame: expected a non-empty allocation_frame DataFrame (missing columns "
            f"{sorted(missing)})"
        )
    kappas = frame["kappa"].unique()
    if len(kappas) != 1:
        raise ValueError(f"frame: expected a single kappa, got {sorted(kappas.tolist())}")
    n_kp = int(frame["keypoint"].max()) + 1
    labels = _names(keypoint_names, n_kp)
    stats = allocation_errorbars(frame)
    alphas = stats["alpha"].unique()
    width = 0.8 / len(alphas)
    n_images = frame["image"].nunique()

    fig = Figure(figsize=(max(8.0, 0.42 * n_kp + 2.0), 7.0), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True, sharey=True)
    for ax, col, title in zip(axes, ("du", "dv"), ("horizontal", "vertical")):
        for s, alpha in enumerate(alphas):
            st = stats[stats["alpha"] == alpha]
            x = st["keypoint"].to_numpy() - 0.4 + width * (s + 0.5)
            ax.errorbar(
                x,
                st[f"{col}_mean"],
                yerr=[st[f"{col}_below"], st[f"{col}_above"]],
                fmt="o",
                ms=3.5,
                capsize=2,
                lw=1,
                label=f"α = {alpha:g}",
            )
        ax.set_xlim(-0.6, n_kp - 0.4)
        symbol = {"du": "δu", "dv": "δv"}[col]
        ax.set_ylabel(f"allocated {symbol} (heatmap px)")
        ax.set_title(f"{title} tolerance {symbol}", fontsize="medium")
        ax.grid(axis="y", alpha=0.3)
    axes[1].set_xticks(np.arange(n_kp), labels, rotation=0 if keypoint_names is None else 60,
                       ha="center" if keypoint_names is None else "right")  # fmt: skip
    axes[1].set_xlabel("keypoint")
    axes[1].autoscale_view()
    axes[1].set_ylim(bottom=0)  # shared: after both panels are drawn
    axes[0].legend(loc="upper right", fontsize="small", ncol=len(alphas))
    fig.suptitle(
        f"Optimal tolerance allocation per keypoint (κ = {kappas[0]:g}, {n_images} images): "
        "mean, bars ± std clipped at 0"
    )
    return fig


def allocation_errorbars(frame: pd.DataFrame) -> pd.DataFrame:
    """The error bars of :func:`plot_allocation`: per α and keypoint, the mean allocated
    tolerance over images and the bar's extent below and above it (heatmap px): ``std``
    above, ``min(std, mean)`` below, so that the bar never goes below 0. Columns
    ``alpha``, ``keypoint``, then ``du_mean``, ``du_below``, ``du_above`` and the same
    for ``dv``; the std of a single image is 0."""
    stats = frame.groupby(["alpha", "keypoint"])[["du", "dv"]].agg(["mean", "std"])
    stats = stats.fillna(0.0)
    out = stats.index.to_frame(index=False)
    for col in ("du", "dv"):
        mean = stats[(col, "mean")].to_numpy(np.float64)
        std = stats[(col, "std")].to_numpy(np.float64)
        out[f"{col}_mean"] = mean
        out[f"{col}_below"] = np.minimum(std, mean)
        out[f"{col}_above"] = std
    return out


def keypoint_deviation_samples(points_3d, keypoints, K, alpha, n_samples, seed, scale):
    """Keypoint deviations caused by pose errors uniform in Ξ, for one image (F-kps).

    The nominal pose ``(R, t)`` is PnP on the ground-truth keypoints. Pose errors
    ``δξ ~ U(−ε, ε)`` with ``ε = α·[EPS_R, EPS_T]`` are added to the nominal Euler angles
    (docs/design.md §3 convention) and translation, the keypoints projected with the perturbed
    pose, and their deviation from the nominal projection returned.

    Parameters
    ----------
    points_3d : array_like, shape (K, 3)
        Object keypoints, metres.
    keypoints : array_like, shape (K, 2)
        Ground-truth keypoints of the image, image pixels.
    K : array_like, shape (3, 3)
        Intrinsics.
    alpha : float
        Tolerance factor α > 0.
    n_samples : int
        Number of pose errors drawn, ≥ 1.
    seed : int
        Seed of ``np.random.default_rng``; same seed → same array.
    scale : (float, float)
        Resize factors ``(sx, sy)`` image → heatmap; deviations are multiplied by them.

    Returns
    -------
    ndarray, shape (n_samples, K, 2), float64
        Deviations ``(du, dv)`` from the nominal projection, heatmap pixels.

    Examples
    --------
    >>> d = keypoint_deviation_samples(P, V[0], K, 0.5, 5000, 0, (0.1, 0.16))  # doctest: +SKIP
    """
    P = _checks.float_array(points_3d, "points_3d", (None, 3))
    V = _checks.float_array(keypoints, "keypoints", (P.shape[0], 2))
    K = _checks.intrinsics(K)
    alpha = float(_checks.positive(alpha, "alpha"))
    n_samples = _positive_int(n_samples, "n_samples")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    sx, sy = _checks.positive(scale, "scale", (2,))

    R, t = solve_pnp(P, V, K)
    eps = tolerance(alpha)
    dxi = np.random.default_rng(seed).uniform(-1.0, 1.0, (n_samples, 6)) * eps
    R_s = matrix_from_euler(euler_from_matrix(R) + dxi[:, :3])  # (S, 3, 3)
    t_s = t + dxi[:, 3:]
    if np.any(np.einsum("nj,sj->sn", P, R_s[:, 2]) + t_s[:, 2:] <= 0):
        raise ValueError(
            f"alpha: expected pose errors that keep the keypoints in front of the camera, "
            f"alpha = {alpha:g} moves some behind it"
        )
    return (project_batch(P, R_s, t_s, K) - project_batch(P, R, t, K)) * np.array([sx, sy])


def plot_keypoint_samples(
    deviations, dv, keypoints=(0, 2, 4), keypoint_names=None, *, alpha: float, kappa: float
) -> Figure:
    """F-kps: sampled keypoint deviations against the allocated box, a panel per keypoint.

    Parameters
    ----------
    deviations : array_like, shape (S, K, 2)
        Output of :func:`keypoint_deviation_samples`, heatmap pixels.
    dv : array_like, shape (K, 2)
        Allocated half-widths ``(δu, δv)`` ≥ 0 of the same image, heatmap pixels
        (``Allocation.dv``).
    keypoints : sequence of int
        0-based indices of the keypoints drawn (default 0, 2, 4: the paper's keypoints
        1, 3 and 5).
    keypoint_names : sequence of str, optional
        Names of all K keypoints, for the panel titles.
    alpha, kappa : float
        The tolerance factor α of the samples and the allocation's κ, both > 0, named in
        the title.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per keypoint: a scatter of the samples ``(du, dv)``, the allocated box
        ``[−δu, δu] × [−δv, δv]`` (solid; a line or a cross where a half-width is 0) and
        the pixels it allows, ``[−δu − ½, δu + ½] × [−δv − ½, δv + ½]`` (dashed: the
        deviations that round into them for a keypoint at a pixel centre). The title gives
        δu, δv and the fraction of samples inside each (:func:`inside_fractions`).
    """
    D = _checks.float_array(deviations, "deviations", (None, None, 2))
    if D.shape[0] < 1 or D.shape[1] < 1:
        raise ValueError(f"deviations: expected shape (S, K, 2) with S, K >= 1, got {D.shape}")
    n_kp = D.shape[1]
    box = _checks.float_array(dv, "dv", (n_kp, 2))
    if np.any(box < 0):
        raise ValueError("dv: expected non-negative half-widths")
    idx = np.asarray(keypoints)
    if (
        idx.ndim != 1
        or idx.size < 1
        or not np.issubdtype(idx.dtype, np.integer)
        or np.any((idx < 0) | (idx >= n_kp))
    ):
        raise ValueError(f"keypoints: expected a non-empty sequence of indices in [0, {n_kp})")
    names = _names(keypoint_names, n_kp)
    alpha = float(_checks.positive(alpha, "alpha"))
    kappa = float(_checks.positive(kappa, "kappa"))
    within, rounding = inside_fractions(D, box)

    fig = Figure(figsize=(3.8 * idx.size, 4.4), layout="constrained")
    axes = fig.subplots(1, idx.size, squeeze=False)[0]
    for ax, k in zip(axes, idx):
        (du, dvk), d = box[k], D[:, k]
        ax.scatter(d[:, 0], d[:, 1], s=2, c="tab:blue", alpha=0.4, lw=0, label="samples")
        cell = Rectangle(
            (-du - 0.5, -dvk - 0.5), 2 * du + 1, 2 * dvk + 1, fill=False, ec="tab:green",
            lw=1.5, ls="--", label="allowed pixels (±(δ + ½))",
        )  # fmt: skip
        ax.add_patch(cell)
        if du > 0 and dvk > 0:
            rect = Rectangle((-du, -dvk), 2 * du, 2 * dvk, fill=False, ec="tab:orange", lw=2)
            rect.set_label("allocated box (±δ)")
            ax.add_patch(rect)
        else:  # a degenerate box: a segment, or a point drawn as a cross
            point = du == 0 and dvk == 0
            ax.plot([-du, du], [-dvk, dvk], color="tab:orange", lw=2.5,
                    marker="+" if point else None, ms=14, mew=2.5,
                    label=f"allocated box (±δ: a {'point' if point else 'segment'})")  # fmt: skip
        ax.axhline(0, color="0.6", lw=0.6)
        ax.axvline(0, color="0.6", lw=0.6)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("deviation u (heatmap px)")
        ax.set_ylabel("deviation v (heatmap px)")
        ax.set_title(
            f"keypoint {names[k]}: δu = {du:g}, δv = {dvk:g} px\n"
            f"{within[k]:.1%} within ±δ, {rounding[k]:.1%} within ±(δ + ½)",
            fontsize="medium",
        )
    axes[0].legend(loc="upper right", fontsize="x-small")
    fig.suptitle(
        f"Keypoint deviations of {D.shape[0]} pose errors uniform in Ξ (α = {alpha:g}: "
        f"ε = α·[10°, 10°, 10°, 4 m, 4 m, 20 m]) against the allocation (κ = {kappa:g})"
    )
    return fig


def inside_fractions(deviations, dv) -> tuple[np.ndarray, np.ndarray]:
    """Per keypoint, the fraction of samples ``deviations`` (S, K, 2) inside the box
    ``|d| ≤ dv`` (K, 2) and inside ``|d| ≤ dv + ½`` (the allowed pixels' extent for a
    keypoint at a pixel centre), both ``(K,)`` in [0, 1]."""
    D = np.asarray(deviations, np.float64)
    box = np.asarray(dv, np.float64)
    within = np.mean(np.all(np.abs(D) <= box, axis=-1), axis=0)
    rounding = np.mean(np.all(np.abs(D) <= box + 0.5, axis=-1), axis=0)
    return within, rounding


def _intrinsics_per_image(K, n: int) -> np.ndarray:
    """``K`` (3, 3) or (n, 3, 3) → (n, 3, 3), each checked."""
    if np.shape(K) == (3, 3):
        K = np.repeat(np.asarray(K)[None], n, axis=0)
    K = _checks.float_array(K, "K", (n, 3, 3))
    for k in K:
        _checks.intrinsics(k)
    return K


def _scale(image_size, heatmap_size) -> tuple[tuple[float, float], np.ndarray]:
    """Resize factors (sx, sy) image → heatmap and the heatmap ``(w, h)`` as ints."""
    if np.shape(image_size) != (2,):
        _fail("image_size", "(W, H)", image_size)
    W, H = (_positive_int(s, "image_size") for s in image_size)
    hs = (heatmap_size, heatmap_size) if np.ndim(heatmap_size) == 0 else heatmap_size
    if np.shape(hs) != (2,):
        _fail("heatmap_size", "an int or (w, h)", heatmap_size)
    hw = np.array([_positive_int(s, "heatmap_size") for s in hs])
    return scale_factors((W, H), tuple(hw)), hw


def _positive_int(x, name: str) -> int:
    if isinstance(x, bool) or not isinstance(x, int | np.integer | float | np.floating):
        _fail(name, "a positive integer", x)
    if not np.isfinite(x) or x != int(x) or x < 1:
        _fail(name, "a positive integer", x)
    return int(x)


def _fail(name: str, expected: str, got):
    raise ValueError(f"{name}: expected {expected}, got {got!r}")


def _names(keypoint_names, n: int) -> list[str]:
    if keypoint_names is None:
        return [str(k) for k in range(n)]
    names = [str(s) for s in keypoint_names]
    if len(names) != n:
        raise ValueError(f"keypoint_names: expected {n} names, got {len(names)}")
    return names
