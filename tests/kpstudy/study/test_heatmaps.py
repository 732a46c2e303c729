"""Symmetry indicators of normalised heatmaps (paper §7.2): synthetic maps with known answers."""

import matplotlib
import numpy as np
import pandas as pd
import pytest
import scipy.stats
import torch

from kpstudy.study.heatmaps import (
    COLUMNS,
    marginal_indicators,
    plot_indicators,
    symmetry_indicators,
)

H, W = 48, 64


def gaussian_logits(u0, v0, su, sv, h=H, w=W):
    """Unnormalised heatmap whose softmax is the discrete Gaussian at (u0, v0), shape (h, w)."""
    u = np.arange(w)[None, :]
    v = np.arange(h)[:, None]
    return -((u - u0) ** 2 / (2 * su**2) + (v - v0) ** 2 / (2 * sv**2))


def separable_logits(log_pu, log_pv):
    """Heatmap (H, W) whose column/row marginals are softmax(log_pu) / softmax(log_pv)."""
    return np.asarray(log_pv)[:, None] + np.asarray(log_pu)[None, :]


def row(df, axis, image=0, keypoint=0):
    sel = df[(df["image"] == image) & (df["keypoint"] == keypoint) & (df["axis"] == axis)]
    assert len(sel) == 1
    return sel.iloc[0]


def lognormal_logits(n, shift=3.0, mu=1.5, s=0.6):
    """Log-density of a log-normal in ``x + shift`` on pixels 0..n-1: a heavy right tail."""
    return scipy.stats.lognorm(s, scale=np.exp(mu)).logpdf(np.arange(n) + shift)


def mixture_logits(n, c=20.0):
    """Log of a main Gaussian at ``c`` plus a weaker, wider one to its right."""
    x = np.arange(n)
    dens = np.exp(-((x - c) ** 2) / (2 * 2.0**2)) + 0.3 * np.exp(-((x - c - 8) ** 2) / (2 * 4.0**2))
    return np.log(dens)


@pytest.mark.parametrize(
    "u0, v0, su, sv", [(32, 24, 3.0, 3.0), (20, 24, 2.0, 3.5), (40, 10, 1.0, 1.5)]
)
def test_gaussian_is_symmetric_and_centred(u0, v0, su, sv):
    df = symmetry_indicators(gaussian_logits(u0, v0, su, sv)[None])
    for axis, c, s in (("u", u0, su), ("v", v0, sv)):
        r = row(df, axis)
        assert abs(r["skewness"]) < 1e-6
        assert r["mean"] == pytest.approx(c, abs=1e-6)
        assert r["mode"] == c
        assert r["mean_minus_median"] == pytest.approx(0.0, abs=1e-6)
        assert r["mean_minus_mode"] == pytest.approx(0.0, abs=1e-6)
        assert abs(r["iqr"] - 1.349 * s) <= 1.0


def test_median_is_exact_pixel():
    r = marginal_indicators(np.exp(gaussian_logits(30, 20, 4.0, 4.0)).sum(axis=0))
    assert r["median"] == 30 and r["mode"] == 30
    assert r["median"].dtype.kind == "i" and r["mode"].dtype.kind == "i"


def test_mean_is_dsnt_and_mode_is_argmax():
    """Conventions: mean = kornia's DSNT in pixels (u, v); mode = argmax column/row."""
    from kornia.geometry.subpix import spatial_expectation2d

    rng = np.random.default_rng(3)
    h = rng.normal(0.0, 2.0, (2, 3, H, W))
    df = symmetry_indicators(h)
    p = torch.softmax(torch.from_numpy(h).reshape(2, 3, -1), dim=-1).reshape(h.shape)
    dsnt = spatial_expectation2d(p, normalized_coordinates=False).numpy()  # (N, K, 2) = (u, v)
    mean = df["mean"].to_numpy().reshape(2, 3, 2)
    np.testing.assert_allclose(mean, dsnt, rtol=0, atol=1e-9)
    pn = p.numpy()
    mode = df["mode"].to_numpy().reshape(2, 3, 2)
    np.testing.assert_array_equal(mode[..., 0], pn.sum(axis=2).argmax(axis=-1))
    np.testing.assert_array_equal(mode[..., 1], pn.sum(axis=3).argmax(axis=-1))


def test_even_tie_picks_left_median():
    """A map centred between two pixels: CDF = 0.5 exactly at the left one."""
    x = np.arange(20)
    r = marginal_indicators(np.exp(-((x - 9.5) ** 2) / 8.0))
    assert r["median"] == 9
    assert r["mean"] == pytest.approx(9.5, abs=1e-12)


def test_truncated_at_border_skews_away_from_it():
    h = np.stack(
        [
            gaussian_logits(1, 24, 5.0, 3.0),  # left border: tail to the right, skew > 0
            gaussian_logits(W - 2, 24, 5.0, 3.0),  # right border: skew < 0
            gaussian_logits(32, 0, 3.0, 5.0),  # top border: tail downwards, skew > 0
            gaussian_logits(32, H - 1, 3.0, 5.0),  # bottom border: skew < 0
        ]
    )
    df = symmetry_indicators(h, keypoint_names=["left", "right", "top", "bottom"])
    for k, axis, sign in (
        ("left", "u", 1),
        ("right", "u", -1),
        ("top", "v", 1),
        ("bottom", "v", -1),
    ):
        r = row(df, axis, keypoint=k)
        assert np.sign(r["skewness"]) == sign and abs(r["skewness"]) > 0.1
        assert np.sign(r["mean_minus_mode"]) == sign
        other = row(df, "v" if axis == "u" else "u", keypoint=k)
        assert abs(other["skewness"]) < 1e-6


@pytest.mark.parametrize("log_p", [lognormal_logits(W), mixture_logits(W)], ids=["lognorm", "mix"])
def test_heavy_right_tail_positive_and_mirror_flips(log_p):
    log_pv = gaussian_logits(0, 24, 1.0, 3.0)[:, 0]
    h = np.stack([separable_logits(log_p, log_pv), separable_logits(log_p[::-1], log_pv)])
    df = symmetry_indicators(h, keypoint_names=["right_tail", "mirrored"])
    a, b = row(df, "u", keypoint="right_tail"), row(df, "u", keypoint="mirrored")
    assert a["skewness"] > 0.1 and a["mean_minus_median"] > 0 and a["mean_minus_mode"] > 0
    assert b["skewness"] < -0.1 and b["mean_minus_median"] < 0 and b["mean_minus_mode"] < 0
    assert b["skewness"] == pytest.approx(-a["skewness"], rel=1e-9)
    assert b["mean"] == pytest.approx(W - 1 - a["mean"], abs=1e-9)
    assert b["mode"] == W - 1 - a["mode"]
    assert b["iqr"] == pytest.approx(a["iqr"], abs=1.0)
    # the v axis is the same symmetric Gaussian in both
    assert abs(row(df, "v", keypoint="mirrored")["skewness"]) < 1e-6


def test_vertical_skew_lands_on_v_axis():
    log_pu = gaussian_logits(32, 0, 3.0, 1.0)[0]
    df = symmetry_indicators(separable_logits(log_pu, lognormal_logits(H))[None])
    assert row(df, "v")["skewness"] > 0.1 and row(df, "v")["mean_minus_median"] > 0
    assert abs(row(df, "u")["skewness"]) < 1e-6


@pytest.mark.parametrize("n", [2, 7, 64, 256])
def test_matches_scipy_rv_discrete(n):
    rng = np.random.default_rng(n)
    p = rng.dirichlet(np.full(n, 0.7), size=6)
    r = marginal_indicators(p)
    x = np.arange(n)
    for i in range(len(p)):
        dist = scipy.stats.rv_discrete(values=(x, p[i]))
        mean, var, skew = (float(s) for s in dist.stats(moments="mvs"))
        np.testing.assert_allclose(r["mean"][i], mean, rtol=1e-9)
        np.testing.assert_allclose(r["var"][i], var, rtol=1e-9)
        np.testing.assert_allclose(r["skewness"][i], skew, rtol=1e-9, atol=1e-12)
        q1, med, q3 = dist.ppf([0.25, 0.5, 0.75])
        assert (r["q1"][i], r["median"][i], r["q3"][i]) == (q1, med, q3)


def test_skewness_matches_sample_skew():
    rng = np.random.default_rng(11)
    p = np.exp(mixture_logits(W))
    p /= p.sum()
    sample = rng.choice(W, size=400_000, p=p)
    r = marginal_indicators(p)
    # standard error of the sample skewness ~ sqrt(6 / n) ~ 0.004
    assert r["skewness"] == pytest.approx(scipy.stats.skew(sample), abs=0.02)
    assert r["median"] == np.median(sample)
    assert r["mean"] == pytest.approx(sample.mean(), abs=0.05)


def test_through_symmetry_indicators_matches_scipy():
    """Random 2-D maps: the DataFrame's u/v rows are the scipy stats of the marginals."""
    rng = np.random.default_rng(5)
    p = rng.dirichlet(np.full(H * W, 0.3)).reshape(H, W)
    df = symmetry_indicators(p[None, None], normalised=True)
    for axis, marg in (("u", p.sum(axis=0)), ("v", p.sum(axis=1))):
        dist = scipy.stats.rv_discrete(values=(np.arange(len(marg)), marg / marg.sum()))
        mean, skew = (float(s) for s in dist.stats(moments="ms"))
        q1, med, q3 = dist.ppf([0.25, 0.5, 0.75])
        r = row(df, axis)
        np.testing.assert_allclose(r["skewness"], skew, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r["mean"], mean, rtol=1e-12)
        np.testing.assert_allclose(r["mean_minus_median"], mean - med, rtol=1e-9, atol=1e-12)
        assert r["iqr"] == q3 - q1


def test_point_mass_has_nan_skewness():
    r = marginal_indicators(np.eye(5)[2])
    assert np.isnan(r["skewness"]) and r["mean"] == 2 and r["median"] == 2 and r["q3"] == r["q1"]


def test_normalised_equals_log_probabilities():
    rng = np.random.default_rng(2)
    logits = rng.normal(0.0, 3.0, (3, 4, H, W))
    p = torch.softmax(torch.from_numpy(logits).reshape(3, 4, -1), -1).reshape(logits.shape)
    a = symmetry_indicators(np.log(p.numpy()))
    b = symmetry_indicators(p.numpy(), normalised=True)
    c = symmetry_indicators(logits + 7.0)  # softmax is shift-invariant
    for other in (b, c):
        pd.testing.assert_frame_equal(
            a.drop(columns=["mode"]), other.drop(columns=["mode"]), rtol=1e-10, atol=1e-10
        )
        np.testing.assert_array_equal(a["mode"], other["mode"])


def test_frame_layout_ids_and_inputs():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(2, 3, 8, 10)).astype(np.float32)
    df = symmetry_indicators(h, image_ids=["a", "b"], keypoint_names=["nose", "tail", "wing"])
    assert list(df.columns) == list(COLUMNS)
    assert df.shape == (2 * 3 * 2, len(COLUMNS))
    assert df["image"].tolist() == ["a"] * 6 + ["b"] * 6
    assert df["keypoint"].tolist()[:6] == ["nose", "nose", "tail", "tail", "wing", "wing"]
    assert df["axis"].tolist() == ["u", "v"] * 6
    assert df["mode"].dtype == np.int64
    u, v = df[df["axis"] == "u"], df[df["axis"] == "v"]
    assert u["mean"].between(0, 9).all() and v["mean"].between(0, 7).all()
    # torch tensor (float32) and a single (K, H, W) map
    pd.testing.assert_frame_equal(
        symmetry_indicators(
            torch.from_numpy(h), image_ids=["a", "b"], keypoint_names=["nose", "tail", "wing"]
        ),
        df,
    )
    one = symmetry_indicators(h[1])
    assert one["image"].tolist() == [0] * 6 and one["keypoint"].tolist() == [0, 0, 1, 1, 2, 2]
    np.testing.assert_allclose(one["skewness"], df["skewness"].to_numpy()[6:], rtol=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (
            {"heatmaps": np.zeros((4, 4))},
            r"heatmaps: expected an \(N, K, H, W\).*got shape \(4, 4\)",
        ),
        ({"heatmaps": np.zeros((1, 1, 1, 4, 4))}, r"heatmaps: .*got shape \(1, 1, 1, 4, 4\)"),
        ({"heatmaps": np.zeros((1, 0, 4, 4))}, r"heatmaps: .*got shape \(1, 0, 4, 4\)"),
        ({"heatmaps": np.full((1, 4, 4), np.nan)}, r"heatmaps: expected finite"),
        ({"heatmaps": np.full((1, 4, 4), np.inf)}, r"heatmaps: expected finite"),
        ({"heatmaps": "abc"}, r"heatmaps: expected"),
        ({"heatmaps": np.zeros((2, 3, 4, 4)), "image_ids": [0]}, r"image_ids: expected .*2 labels"),
        (
            {"heatmaps": np.zeros((2, 3, 4, 4)), "keypoint_names": ["a"] * 4},
            r"keypoint_names: expected .*3 labels",
        ),
        ({"heatmaps": -np.ones((1, 4, 4)), "normalised": True}, r"heatmaps: normalised=True"),
        ({"heatmaps": np.ones((1, 4, 4)), "normalised": True}, r"heatmaps: .*sum to 1"),
    ],
)
def test_errors_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        symmetry_indicators(**kwargs)


def test_plot_indicators():
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(1)
    seed = symmetry_indicators(rng.normal(0, 1, (4, 3, 16, 16)))
    pert = symmetry_indicators(rng.normal(0, 2, (5, 3, 16, 16)))
    fig = plot_indicators({"seed": seed, "perturbed": pert})
    try:
        assert isinstance(fig, matplotlib.figure.Figure)
        axes = fig.get_axes()
        assert len(axes) == 4
        for ax in axes:
            assert len(ax.patches) + len(ax.lines) > 0
            assert ax.get_title() and ax.get_ylabel()
        assert "pixels" in axes[3].get_ylabel()
    finally:
        plt.close(fig)
    with pytest.raises(ValueError, match="frames"):
        plot_indicators({})
    with pytest.raises(ValueError, match="frames"):
        plot_indicators({"x": pd.DataFrame({"a": [1]})})


def test_summary_columns_say_they_are_magnitudes():
    from kpstudy.study.heatmaps import summarise_indicators

    right = symmetry_indicators(separable_logits(lognormal_logits(W), lognormal_logits(H))[None])
    left = symmetry_indicators(
        separable_logits(lognormal_logits(W)[::-1], lognormal_logits(H)[::-1])[None]
    )
    table = summarise_indicators({"right": right, "left": left})
    assert list(table.columns) == [
        "group", "axis", "maps",
        "abs_skewness_median", "abs_skewness_p90",
        "abs_mean_minus_median_median", "abs_mean_minus_median_p90",
        "abs_mean_minus_mode_median", "abs_mean_minus_mode_p90",
        "iqr_median", "iqr_p90",
    ]  # fmt: skip
    # Mirrored maps: opposite skewness, the same magnitude in the table.
    by = table.set_index(["group", "axis"])
    assert row(left, "u")["skewness"] < 0 < row(right, "u")["skewness"]
    assert by.loc[("left", "u"), "abs_skewness_median"] == pytest.approx(
        by.loc[("right", "u"), "abs_skewness_median"], rel=1e-9
    )
    assert (table.filter(like="abs_") > 0).all().all()
