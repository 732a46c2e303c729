"""Symmetry and unimodality indicators of normalised heatmaps (paper §7.1, §8.2; design §4.10).

The network returns one unnormalised heatmap per keypoint; a softmax over all ``H × W`` pixels
turns it into a discrete distribution. Its two marginals are distributions over pixel indices:

* ``u`` (horizontal): the sum over rows, a distribution over the columns ``0 .. W - 1``;
* ``v`` (vertical): the sum over columns, a distribution over the rows ``0 .. H - 1``.

Pixel centres are on integers, ``(u, v)`` = (column, row), 0-based (docs/design.md §3). For each
marginal the paper reports four indicators, all in heatmap pixels except the skewness:

* **skewness** ``E[(x - μ)³] / σ³`` (dimensionless) and **mean − median**: both ≈ 0 for a
  symmetric marginal; positive when the right (or lower) tail is the heavier one;
* **mean − mode** (mode = the most probable pixel) and the **IQR** ``Q3 - Q1``: ≈ 0 and small
  for a single sharp peak; a second peak pulls the mean off the mode and widens the IQR.

Assumption 1 of the paper (``asmp:gaussian``) states that the normalised heatmap has a single
peak and is symmetric about the axes through it. Proposition 1 (``prop:equiv``) follows: on
such a heatmap, DSNT (the softmax mean, kornia's ``spatial_expectation2d``) and argmax return
the same pixel, so certifying the argmax/pooling proxy also certifies the DSNT model. These
indicators measure, per image, keypoint and axis, how far a trained network is from that
assumption.

Quantiles are those of the discrete distribution: ``Q_q`` is the smallest pixel ``x`` with
``CDF(x) ≥ q`` (as ``scipy.stats.rv_discrete(...).ppf``), so the median and the quartiles are
integers and a discrete Gaussian of standard deviation σ has ``IQR ≈ 1.349 σ`` to within one
pixel.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

#: Output columns of :func:`symmetry_indicators`, in order.
COLUMNS = (
    "image",
    "keypoint",
    "axis",
    "skewness",
    "mean_minus_median",
    "mean_minus_mode",
    "iqr",
    "mean",
    "mode",
)

#: Panels of :func:`plot_indicators`: (column, title, y label).
_PANELS = (
    ("skewness", "Skewness", "skewness (dimensionless)"),
    ("mean_minus_median", "Mean − median", "mean − median (heatmap pixels)"),
    ("mean_minus_mode", "Mean − mode", "mean − mode (heatmap pixels)"),
    ("iqr", "Interquartile range", "IQR = Q3 − Q1 (heatmap pixels)"),
)

# Cumulative sums are compared with q·total, minus this relative slack, so that an exact tie
# (CDF(x) = q mathematically, e.g. a symmetric map centred between two pixels) picks x
# whatever the rounding of the sum.
_CDF_SLACK = 1e-12
# Tolerance on the total mass of maps passed with ``normalised=True``.
_MASS_ATOL = 1e-3
# Float64 elements per softmax chunk (about 64 MB).
_CHUNK = 1 << 23


def marginal_indicators(p) -> dict[str, np.ndarray]:
    """Moments, quantiles and mode of discrete distributions on the pixels ``0 .. L - 1``.

    Parameters
    ----------
    p : array_like, shape (..., L)
        Non-negative probabilities along the last axis; each distribution is rescaled by its
        total, which must be > 0.

    Returns
    -------
    dict of str to ndarray, each of shape (...)
        ``mean``, ``var`` (pixels, pixels²), ``skewness`` (dimensionless; NaN where
        ``var == 0``, a point mass), ``median``, ``q1``, ``q3``, ``mode`` (int64 pixels).
        ``median``/``q1``/``q3`` are the smallest ``x`` with ``CDF(x) ≥ 0.5 / 0.25 / 0.75``;
        ``mode`` is the first argmax.

    Examples
    --------
    >>> r = marginal_indicators([0.25, 0.5, 0.25])
    >>> float(r["mean"]), float(r["skewness"]), int(r["median"]), int(r["q3"] - r["q1"])
    (1.0, 0.0, 1, 1)
    """
    p = np.asarray(p, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] < 1:
        raise ValueError(f"p: expected shape (..., L) with L >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)) or np.any(p < 0):
        raise ValueError("p: expected finite, non-negative probabilities")
    total = p.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("p: expected a positive total mass in every distribution")
    p = p / total
    x = np.arange(p.shape[-1], dtype=np.float64)

    mode = np.argmax(p, axis=-1)
    # Moments about the mode first: the offsets stay small, so a sharp peak keeps its accuracy.
    shift = mode[..., None].astype(np.float64)
    mean_off = np.sum(p * (x - shift), axis=-1, keepdims=True)
    d = x - shift - mean_off
    var = np.sum(p * d**2, axis=-1)
    m3 = np.sum(p * d**3, axis=-1)
    skew = np.full(var.shape, np.nan)
    ok = var > 0
    skew[ok] = m3[ok] / var[ok] ** 1.5

    cdf = np.cumsum(p, axis=-1)
    cdf_total = cdf[..., -1:]

    def quantile(q):
        return np.sum(cdf < (q - _CDF_SLACK) * cdf_total, axis=-1)

    return {
        "mean": mean_off[..., 0] + shift[..., 0],
        "var": var,
        "skewness": skew,
        "median": quantile(0.5),
        "q1": quantile(0.25),
        "q3": quantile(0.75),
        "mode": mode,
    }


def symmetry_indicators(
    heatmaps, *, normalised: bool = False, image_ids=None, keypoint_names=None
) -> pd.DataFrame:
    """The paper's four symmetry indicators for every image, keypoint and axis.

    Parameters
    ----------
    heatmaps : array_like or torch.Tensor, shape (N, K, H, W) or (K, H, W)
        Unnormalised heatmaps (network output, any float dtype; computed in float64), or,
        with ``normalised=True``, probabilities that sum to 1 over each ``H × W`` map
        (within 1e-3; they are rescaled to exactly 1). A (K, H, W) input means N = 1.
    normalised : bool
        ``False``: apply a softmax over the ``H × W`` pixels of each map first.
    image_ids : sequence of length N, optional
        Labels of the ``image`` column; default ``0 .. N - 1``.
    keypoint_names : sequence of length K, optional
        Labels of the ``keypoint`` column; default ``0 .. K - 1``.

    Returns
    -------
    pandas.DataFrame
        ``2 N K`` rows ordered by image, keypoint, then axis ``'u'`` (the marginal over the
        columns, length W) and ``'v'`` (over the rows, length H), with columns ``image``,
        ``keypoint``, ``axis``, ``skewness`` (dimensionless; NaN for a point mass),
        ``mean_minus_median``, ``mean_minus_mode``, ``iqr`` (heatmap pixels), ``mean``
        (heatmap pixels, the DSNT coordinate) and ``mode`` (int, the argmax pixel).

    Raises
    ------
    ValueError
        Wrong shape, non-finite values, non-normalised maps with ``normalised=True``, or
        ``image_ids``/``keypoint_names`` of the wrong length.

    Examples
    --------
    >>> x = np.arange(16.0)
    >>> logits = -((x[None, :] - 8) ** 2 + (x[:, None] - 6) ** 2) / 2.0  # discrete Gaussian
    >>> df = symmetry_indicators(logits[None])  # N = 1 (and K = 1)
    >>> df[["axis", "mean", "mode", "iqr"]].round(6).values.tolist()
    [['u', 8.0, 8, 2.0], ['v', 6.0, 6, 2.0]]
    """
    h = _as_maps(heatmaps)
    n, k, height, width = h.shape
    image_ids = _labels(image_ids, n, "image_ids")
    keypoint_names = _labels(keypoint_names, k, "keypoint_names")

    pu, pv = _marginals(h.reshape(n * k, height, width), normalised)
    # (N·K, 2, L) would need equal lengths: compute per axis, then interleave u, v.
    ru, rv = marginal_indicators(pu), marginal_indicators(pv)

    def both(key):
        return np.stack([ru[key], rv[key]], axis=1).reshape(-1)

    mean = both("mean")
    return pd.DataFrame(
        {
            "image": image_ids.repeat(2 * k),
            "keypoint": np.tile(keypoint_names.repeat(2), n),
            "axis": np.tile(np.array(["u", "v"]), n * k),
            "skewness": both("skewness"),
            "mean_minus_median": mean - both("median"),
            "mean_minus_mode": mean - both("mode"),
            "iqr": (both("q3") - both("q1")).astype(np.float64),
            "mean": mean,
            "mode": both("mode").astype(np.int64),
        },
        columns=list(COLUMNS),
    )


def backbone_heatmaps(backbone, images, batch_size: int = 16) -> torch.Tensor:
    """Unnormalised heatmaps ``(N, K, H, W)`` float32 of preprocessed images ``(N, s, s, 3)``
    in [0, 255] (the backbone's input size), computed in eval mode in batches."""
    from kpstudy.models.preprocess import to_model_input

    images = np.asarray(images, np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected (N, s, s, 3) images, got shape {images.shape}")
    backbone.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(images), batch_size):
            out.append(backbone(to_model_input(images[i : i + batch_size])).float())
    return torch.cat(out)


def summarise_indicators(frames) -> pd.DataFrame:
    """Per group and axis, the median and 90th percentile over maps of each indicator's
    magnitude, from :func:`symmetry_indicators` frames ``{group: frame}``.

    Returns
    -------
    DataFrame
        One row per group and axis: ``group``, ``axis``, ``maps`` (count), then
        ``abs_skewness_median``, ``abs_skewness_p90`` (dimensionless),
        ``abs_mean_minus_median_*``, ``abs_mean_minus_mode_*`` (heatmap px) and
        ``iqr_median``, ``iqr_p90`` (heatmap px, never negative): the names say that the
        signed indicators are taken as magnitudes ``|·|``.
    """
    rows = []
    for name, df in frames.items():
        for axis in ("u", "v"):
            part = df[df["axis"] == axis]
            row = {"group": name, "axis": axis, "maps": len(part)}
            for col, _, _ in _PANELS:
                values = part[col].abs().dropna()
                key = col if col == "iqr" else f"abs_{col}"
                row[f"{key}_median"] = float(values.median())
                row[f"{key}_p90"] = float(values.quantile(0.9))
            rows.append(row)
    return pd.DataFrame(rows)


def plot_indicators(frames):
    """The paper's indicator figure (``fig:indicators``): box plots per indicator and axis.

    Parameters
    ----------
    frames : dict of str to pandas.DataFrame
        Outputs of :func:`symmetry_indicators`, one per group, e.g.
        ``{"seed": df_seed, "perturbed": df_perturbed}``. NaN values (point masses) are left
        out.

    Returns
    -------
    matplotlib.figure.Figure
        Four panels (skewness, mean − median, mean − mode, IQR); in each, the ``u`` (columns)
        and ``v`` (rows) axes side by side, one coloured box per group. The figure is
        registered with pyplot: close it with ``plt.close(fig)``.
    """
    if not isinstance(frames, dict) or not frames:
        raise ValueError("frames: expected a non-empty dict of name -> DataFrame")
    for name, df in frames.items():
        missing = {"axis", *(c for c, _, _ in _PANELS)} - set(getattr(df, "columns", ()))
        if not isinstance(df, pd.DataFrame) or missing:
            raise ValueError(
                f"frames: entry {name!r} is not a symmetry_indicators DataFrame "
                f"(missing columns {sorted(missing)})"
            )

    import matplotlib.pyplot as plt

    names = list(frames)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    width = 0.8 / len(names)
    fig, axes = plt.subplots(2, 2, figsize=(10, 7), layout="constrained")
    for ax, (col, title, ylabel) in zip(axes.flat, _PANELS):
        for g, name in enumerate(names):
            df = frames[name]
            data = [df.loc[df["axis"] == a, col].dropna().to_numpy(float) for a in ("u", "v")]
            pos = np.arange(2) - 0.4 + width * (g + 0.5)
            color = colors[g % len(colors)]
            ax.boxplot(
                data,
                positions=pos,
                widths=0.9 * width,
                patch_artist=True,
                boxprops={"facecolor": color, "alpha": 0.6},
                medianprops={"color": "k"},
                flierprops={"marker": ".", "markersize": 2, "markeredgecolor": color},
            )
            ax.plot([], [], "s", color=color, alpha=0.6, label=name)
        if col != "iqr":
            ax.axhline(0.0, color="0.5", lw=0.8, ls="--")
        ax.set_xticks([0, 1], ["u (columns)", "v (rows)"])
        ax.set_xlim(-0.5, 1.5)
        ax.set_xlabel("heatmap axis")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
    axes.flat[0].legend(loc="best", fontsize="small")
    fig.suptitle("Symmetry indicators of the normalised heatmaps")
    return fig


def _as_maps(heatmaps) -> torch.Tensor:
    """``heatmaps`` as a float64 CPU tensor of shape (N, K, H, W)."""
    msg = "heatmaps: expected an (N, K, H, W) or (K, H, W) array"
    try:
        if isinstance(heatmaps, torch.Tensor):
            h = heatmaps.detach().to(device="cpu", dtype=torch.float64)
        else:
            h = torch.from_numpy(np.array(heatmaps, dtype=np.float64))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{msg} of numbers") from exc
    if h.ndim == 3:
        h = h[None]
    if h.ndim != 4 or min(h.shape) < 1:
        raise ValueError(f"{msg}, got shape {tuple(h.shape)}")
    if not bool(torch.isfinite(h).all()):
        raise ValueError("heatmaps: expected finite values, got NaN or inf")
    return h


def _labels(labels, n: int, name: str) -> np.ndarray:
    """``labels`` (or ``0 .. n - 1``) as a 1-D array of length ``n``."""
    if labels is None:
        return np.arange(n)
    a = np.asarray(labels)
    if a.ndim != 1 or len(a) != n:
        raise ValueError(f"{name}: expected a 1-D sequence of {n} labels, got shape {a.shape}")
    return a


def _marginals(h: torch.Tensor, normalised: bool) -> tuple[np.ndarray, np.ndarray]:
    """Column and row marginals (M, W), (M, H) of the maps ``h`` (M, H, W), in float64."""
    m, height, width = h.shape
    pu, pv = np.empty((m, width)), np.empty((m, height))
    step = max(1, _CHUNK // (height * width))
    for s in range(0, m, step):
        x = h[s : s + step]
        if normalised:
            if bool((x < 0).any()):
                raise ValueError("heatmaps: normalised=True expects non-negative probabilities")
            mass = x.sum(dim=(1, 2), keepdim=True)
            if not bool(((mass - 1).abs() <= _MASS_ATOL).all()):
                raise ValueError(
                    "heatmaps: normalised=True expects each map to sum to 1, got sums in "
                    f"[{float(mass.min()):.6g}, {float(mass.max()):.6g}]"
                )
            p = x / mass
        else:
            p = torch.softmax(x.reshape(len(x), -1), dim=-1).reshape(x.shape)
        pu[s : s + step] = p.sum(dim=1).numpy()
        pv[s : s + step] = p.sum(dim=2).numpy()
    return pu, pv
