"""F-alloc and F-kps: allocation frame, deviation samples and their figures."""

import numpy as np
import pandas as pd
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.pose.geometry import project_batch
from kpstudy.study.allocation_figures import (
    FRAME_COLUMNS,
    allocation_errorbars,
    allocation_frame,
    inside_fractions,
    keypoint_deviation_samples,
    plot_allocation,
    plot_keypoint_samples,
)

IMAGE_SIZE = (640, 400)

HEATMAP = 64

SCALE = (HEATMAP / IMAGE_SIZE[0], HEATMAP / IMAGE_SIZE[1])

ALPHAS = (0.5, 1.0, 1.5, 2.0)

N_IMAGES = 2


@pytest.fixture(scope="module")
def scene():
    P = airliner_keypoints()
    K = intrinsics(*IMAGE_SIZE, 70.0)
    R, t = overhead_poses(N_IMAGES, 3)
    return P, project_batch(P, R, t, K), K


@pytest.fixture(scope="module")
def frame(scene):
    P, V, K = scene
    return allocation_frame(P, V, K, IMAGE_SIZE, HEATMAP, alphas=ALPHAS)


def test_frame_layout(scene, frame):
    P = scene[0]
    assert list(frame.columns) == list(FRAME_COLUMNS)
    assert len(frame) == N_IMAGES * len(ALPHAS) * len(P)
    assert sorted(frame["image"].unique()) == list(range(N_IMAGES))
    assert sorted(frame["alpha"].unique()) == list(ALPHAS)
    assert (frame["kappa"] == 1.0).all()
    per_block = frame["keypoint"].to_numpy().reshape(N_IMAGES * len(ALPHAS), len(P))
    assert (per_block == np.arange(len(P))).all()


def test_frame_values(frame):
    for col in ("du", "dv"):
        assert pd.api.types.is_integer_dtype(frame[col])
        assert (frame[col] >= 0).all() and (frame[col] <= HEATMAP).all()
    assert frame[["du", "dv"]].to_numpy().sum() > 0
    mean = frame.groupby("alpha")[["du", "dv"]].mean().sum(axis=1).to_numpy()
    assert np.all(np.diff(mean) >= 0)
    assert mean[-1] > mean[0]


def test_frame_matches_per_image_intrinsics(scene, frame):
    P, V, K = scene
    per_image = allocation_frame(P, V[:1], np.stack([K]), IMAGE_SIZE, (HEATMAP, HEATMAP), [1.0])
    ref = frame[(frame.image == 0) & (frame.alpha == 1.0)]
    np.testing.assert_array_equal(per_image[["du", "dv"]], ref[["du", "dv"]])


def test_deviation_samples_shape_and_seed(scene):
    P, V, K = scene
    d = keypoint_deviation_samples(P, V[0], K, 0.5, 200, 7, SCALE)
    assert d.shape == (200, len(P), 2) and d.dtype == np.float64
    np.testing.assert_array_equal(d, keypoint_deviation_samples(P, V[0], K, 0.5, 200, 7, SCALE))
    assert not np.allclose(d, keypoint_deviation_samples(P, V[0], K, 0.5, 200, 8, SCALE))
    assert np.abs(d).max() > 0.5  # ε = 5°, 2 m moves keypoints by pixels


def test_deviation_samples_are_in_heatmap_pixels(scene):
    P, V, K = scene
    image_px = keypoint_deviation_samples(P, V[0], K, 0.5, 50, 1, (1.0, 1.0))
    heat_px = keypoint_deviation_samples(P, V[0], K, 0.5, 50, 1, SCALE)
    np.testing.assert_allclose(heat_px, image_px * np.array(SCALE))


def test_deviation_samples_scale_linearly(scene):
    P, V, K = scene
    small = keypoint_deviation_samples(P, V[1], K, 0.01, 300, 2, SCALE)
    double = keypoint_deviation_samples(P, V[1], K, 0.02, 300, 2, SCALE)
    ratio = np.abs(double).max() / np.abs(small).max()
    assert ratio == pytest.approx(2.0, rel=0.1)


def test_tiny_alpha_stays_in_unit_box(scene):
    P, V, K = scene
    d = keypoint_deviation_samples(P, V[0], K, 1e-3, 500, 0, SCALE)
    assert np.all(np.abs(d) <= 1.0)


def test_plot_allocation(frame, tmp_path):
    fig = plot_allocation(frame)
    assert isinstance(fig, Figure)
    axes = fig.get_axes()
    assert len(axes) == 2
    for ax, unit in zip(axes, ("δu", "δv")):
        assert ax.get_ylabel() == f"allocated {unit} (heatmap px)"
        assert len(ax.containers) == len(ALPHAS)  # one errorbar series per α
        assert ax.get_ylim()[0] == 0
        for container in ax.containers:  # no bar reaches below 0
            (bars,) = container.lines[2]
            assert min(seg[:, 1].min() for seg in bars.get_segments()) >= 0
    labels = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert labels == [f"α = {a:g}" for a in ALPHAS]
    assert "κ = 1" in fig.get_suptitle() and f"{N_IMAGES} images" in fig.get_suptitle()
    fig.savefig(tmp_path / "f_alloc.png", dpi=40)
    assert (tmp_path / "f_alloc.png").stat().st_size > 0
    # The labels, the title and the panels do not overlap once drawn.
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    title = fig._suptitle.get_window_extent(renderer)
    for ax in axes:
        label = ax.yaxis.label.get_window_extent(renderer)
        assert label.x0 >= 0 and label.y0 >= 0  # not clipped at the figure's edge
        assert not label.overlaps(title) and not ax.title.get_window_extent(renderer).overlaps(
            title
        )


def test_error_bars_are_clipped_at_zero():
    frame = pd.DataFrame(
        {"image": [0, 1, 2], "alpha": 1.0, "kappa": 1.0, "keypoint": 0, "du": [0, 0, 3],
         "dv": [2, 2, 2]}
    )  # fmt: skip
    bars = allocation_errorbars(frame).iloc[0]
    assert bars.du_mean == 1.0 and bars.du_above == pytest.approx(np.sqrt(3.0))
    assert bars.du_below == 1.0  # std √3 > mean 1: the bar stops at 0
    assert (bars.dv_mean, bars.dv_below, bars.dv_above) == (2.0, 0.0, 0.0)


def test_plot_keypoint_samples(scene, frame, tmp_path):
    P, V, K = scene
    d = keypoint_deviation_samples(P, V[0], K, 0.5, 300, 0, SCALE)
    dv = frame[(frame.image == 0) & (frame.alpha == 0.5)][["du", "dv"]].to_numpy()
    names = [f"kp{k}" for k in range(len(P))]
    dv = np.maximum(dv, 1)
    fig = plot_keypoint_samples(d, dv, keypoints=(0, 4), keypoint_names=names, alpha=0.5, kappa=1.0)
    axes = fig.get_axes()
    assert len(axes) == 2
    assert "α = 0.5" in fig.get_suptitle() and "κ = 1" in fig.get_suptitle()
    for ax, k in zip(axes, (0, 4)):
        inside = np.mean(np.all(np.abs(d[:, k]) <= dv[k], axis=-1))
        near = np.mean(np.all(np.abs(d[:, k]) <= dv[k] + 0.5, axis=-1))
        assert ax.get_title() == (
            f"keypoint kp{k}: δu = {dv[k, 0]:g}, δv = {dv[k, 1]:g} px\n"
            f"{inside:.1%} within ±δ, {near:.1%} within ±(δ + ½)"
        )
        cell, rect = ax.patches
        assert (rect.get_width(), rect.get_height()) == (2 * dv[k, 0], 2 * dv[k, 1])
        assert (cell.get_width(), cell.get_height()) == (2 * dv[k, 0] + 1, 2 * dv[k, 1] + 1)
    fig.savefig(tmp_path / "f_kps.png", dpi=40)
    assert (tmp_path / "f_kps.png").stat().st_size > 0
    huge = plot_keypoint_samples(d, np.full_like(dv, 50), keypoints=[3], alpha=0.5, kappa=1)
    assert len(huge.get_axes()) == 1 and "100.0% within ±δ" in huge.get_axes()[0].get_title()


def test_zero_tolerance_is_drawn_and_named():
    """δu = δv = 0 (a one-pixel cell): a cross at the origin, not an invisible box, and the
    title says so and counts the samples that round into that pixel."""
    d = np.array([[[0.2, -0.1]], [[0.7, 0.0]], [[0.0, 0.4]], [[-0.3, -0.6]]])
    fig = plot_keypoint_samples(d, np.zeros((1, 2)), keypoints=[0], alpha=1.0, kappa=1.5)
    (ax,) = fig.get_axes()
    assert ax.get_title() == "keypoint 0: δu = 0, δv = 0 px\n0.0% within ±δ, 50.0% within ±(δ + ½)"
    (cross,) = [line for line in ax.lines if line.get_label().startswith("allocated box")]
    assert cross.get_marker() == "+" and cross.get_markersize() >= 10
    (cell,) = ax.patches
    assert (cell.get_width(), cell.get_height()) == (1.0, 1.0)
    within, rounding = inside_fractions(d, np.zeros((1, 2)))
    np.testing.assert_array_equal(within, [0.0])
    np.testing.assert_array_equal(rounding, [0.5])


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(alpha=0.0), "alpha"),
        (dict(alpha=-1.0), "alpha"),
        (dict(n_samples=0), "n_samples"),
        (dict(n_samples=2.5), "n_samples"),
        (dict(keypoints=np.zeros((5, 2))), "keypoints"),
        (dict(K=np.eye(2)), "K"),
        (dict(scale=(0.1,)), "scale"),
        (dict(seed="a"), "seed"),
    ],
)
def test_deviation_samples_bad_input(scene, change, match):
    P, V, K = scene
    kwargs = dict(points_3d=P, keypoints=V[0], K=K, alpha=0.5, n_samples=10, seed=0, scale=SCALE)
    with pytest.raises(ValueError, match=f"^{match}"):
        keypoint_deviation_samples(**{**kwargs, **change})


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(alphas=(0.5, 0.0)), "alphas"),
        (dict(keypoints=np.zeros((1, 5, 2))), "keypoints"),
        (dict(K=np.zeros((3, 3, 3))), "K"),
        (dict(image_size=640), "image_size"),
        (dict(heatmap_size=0), "heatmap_size"),
        (dict(kappa=0.0), "kappa"),
    ],
)
def test_allocation_frame_bad_input(scene, change, match):
    P, V, K = scene
    kwargs = dict(points_3d=P, keypoints=V, K=K, image_size=IMAGE_SIZE, heatmap_size=HEATMAP)
    with pytest.raises(ValueError, match=f"^{match}"):
        allocation_frame(**{**kwargs, **change})


def test_plots_bad_input(frame):
    with pytest.raises(ValueError, match="^frame"):
        plot_allocation(pd.DataFrame({"alpha": [1.0]}))
    with pytest.raises(ValueError, match="^frame"):
        plot_allocation(pd.concat([frame, frame.assign(kappa=1.5)]))
    with pytest.raises(ValueError, match="^keypoint_names"):
        plot_allocation(frame, keypoint_names=["a"])
    d = np.zeros((4, 3, 2))
    ak = dict(alpha=1.0, kappa=1.0)
    with pytest.raises(ValueError, match="^dv"):
        plot_keypoint_samples(d, np.zeros((2, 2)), **ak)
    with pytest.raises(ValueError, match="^dv"):
        plot_keypoint_samples(d, -np.ones((3, 2)), keypoints=[0], **ak)
    with pytest.raises(ValueError, match="^keypoints"):
        plot_keypoint_samples(d, np.ones((3, 2)), keypoints=[3], **ak)
    with pytest.raises(ValueError, match="^deviations"):
        plot_keypoint_samples(np.zeros((4, 3)), np.ones((3, 2)), **ak)
    with pytest.raises(ValueError, match="^alpha"):
        plot_keypoint_samples(d, np.ones((3, 2)), keypoints=[0], alpha=0.0, kappa=1.0)
    with pytest.raises(ValueError, match="^kappa"):
        plot_keypoint_samples(d, np.ones((3, 2)), keypoints=[0], alpha=1.0, kappa=-1.0)


def test_the_f_alloc_table_is_the_mean_and_spread_per_alpha_and_keypoint():
    from kpstudy.study.allocation_figures import allocation_table

    frame = pd.DataFrame(
        {
            "alpha": [1.0, 1.0, 1.0, 1.0, 2.0, 2.0],
            "keypoint": [0, 0, 1, 1, 0, 0],
            "du": [1, 3, 0, 0, 2, 2],
            "dv": [2, 2, 4, 0, 5, 7],
        }
    )
    table = allocation_table(frame, ["nose", "tail"])
    assert list(table.columns) == [
        *("alpha", "keypoint", "name", "du_mean", "du_std", "dv_mean", "dv_std"),
    ]
    assert table["name"].tolist() == ["nose", "tail", "nose"]
    assert table["du_mean"].tolist() == [2.0, 0.0, 2.0]
    assert table["dv_mean"].tolist() == [2.0, 2.0, 6.0]
    assert table["du_std"].round(6).tolist() == [1.414214, 0.0, 0.0]
