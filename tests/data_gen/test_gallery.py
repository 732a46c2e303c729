"""data_gen.gallery: its drawing helpers on synthetic images (labels kept apart, changes
circled, the perturbation sheet's difference panels), and every figure of a small
rendered dataset."""

import numpy as np
import pytest
from matplotlib.patches import Circle

from data_gen.dataset import generate_dataset, read_image
from data_gen.gallery import change_circles, perturbation_sheet, place_labels


def test_labels_of_a_dense_cluster_do_not_overlap():
    rng = np.random.default_rng(0)
    points = rng.uniform(100, 130, (23, 2))  # 23 keypoints in a 30 px square
    box = (14.0, 13.0)
    centres = place_labels(points, box, radius=13.0)
    assert centres.shape == (23, 2)
    dx = np.abs(centres[:, None, 0] - centres[None, :, 0])
    dy = np.abs(centres[:, None, 1] - centres[None, :, 1])
    overlap = (dx < box[0]) & (dy < box[1])
    np.fill_diagonal(overlap, False)
    assert not overlap.any()
    # Each label stays near its point: on one of the four rings.
    distance = np.linalg.norm(centres - points, axis=1)
    assert np.all((distance > 12.9) & (distance < 4 * 13.0 + 1e-9))
    # An isolated point keeps its label on the first ring.
    alone = place_labels([[10.0, 10.0]], box, radius=13.0)
    assert np.linalg.norm(alone[0] - [10.0, 10.0]) == pytest.approx(13.0)
    with pytest.raises(ValueError, match="^points"):
        place_labels(np.zeros((3, 3)), box, 1.0)
    with pytest.raises(ValueError, match="^box, radius"):
        place_labels(points, (0.0, 1.0), 1.0)


def test_change_circles_one_per_area():
    changed = np.zeros((100, 200), bool)
    changed[10:13, 20:23] = True  # a 3 × 3 block
    changed[60:80, 150:190] = True  # an occluder
    changed[62, 192] = True  # joins the occluder (within 3 px)
    circles = change_circles(changed)
    assert circles.shape == (2, 3)
    (cx, cy, r), (bx, by, br) = circles  # the larger area first
    assert (cx, cy) == (171.0, 69.5) and r == pytest.approx(1.25 * 0.5 * np.hypot(20, 43))
    assert (bx, by) == (21.0, 11.0) and br == pytest.approx(0.06 * 200)  # the smallest radius
    assert change_circles(np.zeros((5, 5), bool)).shape == (0, 3)
    with pytest.raises(ValueError, match="^changed"):
        change_circles(np.zeros(5, bool))


def _titles(fig):
    return [ax.get_title() for ax in fig.axes]


def test_sheet_shows_differences_and_circles_local_changes():
    seed = np.full((40, 60, 3), 120.0)
    block = seed.copy()
    block[5:8, 50:53] = 250.0  # a 3 × 3 block, 130 grey levels brighter
    brighter, darker = seed + 2.0, seed - 2.0  # brightness ±2: invisible by eye
    fig = perturbation_sheet(
        [("blocks", np.stack([seed, block])), ("brightness ±2", np.stack([seed, brighter, darker]))]
    )
    titles = _titles(fig)
    assert "blocks: seed" in titles and "brightness ±2: seed" in titles
    assert "|Δ| ≤ 130 on 9 px (0.38%)" in titles
    assert titles.count("|Δ| ≤ 2 on 2400 px (100.00%)") == 2  # both brightness vertices
    vertex = next(ax for ax in fig.axes if ax.get_title() == "vertex 1")
    (circle,) = [p for p in vertex.patches if isinstance(p, Circle)]
    assert tuple(circle.center) == (51.0, 6.0)
    # A global change is not circled; its difference panel shares the hull's scale 0–2.
    diff = next(ax for ax in fig.axes if ax.get_title() == "|Δ| ≤ 2 on 2400 px (100.00%)")
    assert not diff.patches and diff.images[0].get_clim() == (0.0, 2.0)
    with pytest.raises(ValueError, match="^rows"):
        perturbation_sheet([])
    with pytest.raises(ValueError, match="^rows: expected vertices"):
        perturbation_sheet([("x", seed)])


SIZE = "240x150"


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return generate_dataset(tmp_path_factory.mktemp("ds") / "data", 8, SIZE, seed=3, progress=False)


def test_gallery_draws_every_figure(small, tmp_path):
    from data_gen.gallery import write_gallery
    from data_gen.perturb import make_perturbations

    make_perturbations(small, "brightness", seeds=1, input_size=32, overwrite=True)
    paths = write_gallery(tmp_path / "figs", small)
    names = ["crew_closeup.png", "occluders.png", "perturbations.png", "renders.png"]
    assert sorted(p.name for p in paths) == names
    for path in paths:
        picture = read_image(path)
        assert picture.shape[0] > 200 and picture.std() > 10  # drawn, not blank
