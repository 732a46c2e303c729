"""kpstudy.certify.hull: certify's record on a rendered tiny dataset and a tiny trained CNN
(the ``study`` fixture), under both tolerance readings; a seed without a valid nominal
pose is refused."""

import numpy as np
import pytest
import torch

from data_gen.perturb import hull_vertices
from kpstudy.certify.allocation_method import SeedImage, build_instance
from kpstudy.certify.hull import certify
from kpstudy.certify.pose_bound_attack import argmax_outside
from kpstudy.models.training import load_checkpoint
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T
from kpstudy.pose.pnp import PnPResult
from kpstudy.pose.sensitivity import pose_sensitivity
from tests.conftest import seed_image, views


def test_cells_covering_the_heatmap_hold_and_are_checked_end_to_end(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    # α = 1e4: every tolerance reaches the heatmap size: one cell per keypoint, nothing to beat.
    record = certify(
        backbone, vertices, seed, alpha=1e4, timeout=600, max_nodes=1000, check_samples=16
    )
    assert record["status"] == "holds"
    lo, hi = np.asarray(record["cells"])  # each keypoint's cell is the whole heatmap
    assert np.all(lo == 0) and np.all(hi == 63) and np.all(np.asarray(record["dv"]) == 31.5)
    assert record["first_order"] <= 1.0
    assert record["group_status"] == ["holds"] * 23
    assert record["empirical_samples"] == 16
    assert 0.0 <= record["empirical_inside"] <= 1.0
    assert len(record["seed_error"]) == 6 and isinstance(record["seed_inside"], bool)
    lower, upper = record["margin_bracket"]
    assert upper is None or lower is None or lower <= upper + 1e-6


def test_a_violated_instance_carries_a_point_of_the_hull(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
    vertices = hull_vertices(data, seed.image_id, "blocks", 2, True)
    record = certify(
        backbone, vertices, seed, alpha=0.5, timeout=600, max_nodes=1000, check_samples=4
    )
    # A two-epoch network misses most keypoints' cells even on the seed image.
    assert record["status"] == "violated"
    lam = np.asarray(record["counterexample"])
    assert lam.shape == (2,) and np.all(lam >= 0) and lam.sum() <= 1 + 1e-12
    assert record["empirical_inside"] is None
    assert "violated" in record["group_status"]
    assert np.all(np.asarray(record["dv"]) <= 64) and record["delta"] == min(
        min(r) for r in record["dv"]
    )


def test_the_paper_reading_allocates_per_image_pixel_and_measures_its_price(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    heatmap = build_instance(backbone, vertices, seed, alpha=1.5)
    paper = build_instance(backbone, vertices, seed, alpha=1.5, tolerance_units="paper")
    P, V, K = seed.points_3d, np.asarray(seed.keypoints, float), seed.K
    R, t = heatmap.R, heatmap.t
    M = pose_sensitivity(P, V, K, R, t, scale=None)
    expected = allocate_tolerances(M, 1.5 * EPS_R, 1.5 * EPS_T, max_dv=64).dv
    assert np.array_equal(paper.allocation.dv, expected)
    lo, hi = paper.cells  # the paper's cells: ±δv around the rounded keypoints
    assert np.array_equal(hi - paper.centers, expected) and np.array_equal(
        paper.centers - lo, expected
    )
    assert paper.tolerance_units == "paper" and heatmap.tolerance_units == "heatmap"
    # Per image pixel the sensitivity is smaller (a 640×400 render on a 64×64 heatmap):
    # the paper's reading allocates wider cells, beyond the first-order bound; the
    # pose-bound's M stays per heatmap pixel.
    assert heatmap.feasible and heatmap.first_order <= 1.0 < paper.first_order
    assert np.sum(paper.cells[1] - paper.cells[0]) > np.sum(heatmap.cells[1] - heatmap.cells[0])
    assert np.array_equal(paper.M, heatmap.M)

    record = certify(
        backbone,
        vertices,
        seed,
        alpha=1e4,
        timeout=600,
        max_nodes=1000,
        check_samples=8,
        tolerance_units="paper",
    )
    assert record["status"] == "holds" and record["tolerance_units"] == "paper"
    hull = paper.hull
    images = hull.image(hull.sample(8, 0))
    xi = 1e4 * np.r_[EPS_R, EPS_T]
    outside = argmax_outside(backbone, images, seed, R, t, xi)
    assert record["argmax_outside"] == len(outside) / 8
    with pytest.raises(ValueError, match="^tolerance_units: expected one of"):
        build_instance(backbone, vertices, seed, tolerance_units="pixels")


def test_certify_bad_input_is_named(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
    good = hull_vertices(data, seed.image_id, "brightness", level=1.0)
    with pytest.raises(ValueError, match="alpha"):
        certify(backbone, good, seed, alpha=0.0)
    with pytest.raises(ValueError, match="vertices"):
        certify(backbone, good[:1], seed)
    with pytest.raises(ValueError, match="check_samples"):
        certify(backbone, good, seed, check_samples=-1)
    with pytest.raises(ValueError, match="backbone"):
        certify(torch.nn.Identity(), good, seed)


def test_certify_refuses_a_seed_without_a_valid_nominal_pose(P, K, monkeypatch):
    from kpstudy.certify import allocation_method
    from kpstudy.certify.hull import certify

    R, t, V = views(1, 26, K, P)
    monkeypatch.setattr(
        allocation_method, "solve_pnp", lambda *a, **kw: PnPResult(R[0], t[0], False, 90.0, -3.0)
    )
    backbone = torch.nn.Identity()
    backbone.input_size, backbone.heatmap_size = 64, 64
    seed = SeedImage(0, V[0], K, P, (640, 400))
    with pytest.raises(ValueError, match="^seed: PnP on the ground-truth keypoints gives no"):
        certify(backbone, np.zeros((2, 8, 8, 3)), seed, check_samples=0)
