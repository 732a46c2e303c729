"""kpstudy.certify.pose_bound_method and its parts: the linearised pose bound over keypoint
regions (kpstudy.certify.pose_bound_rules), the region search, and certify's record."""

import itertools

import numpy as np
import pytest
import torch

from data_gen.perturb import hull_vertices
from kpstudy.certify import pose_bound_method as pb
from kpstudy.certify.allocation_method import target_pose_errors
from kpstudy.certify.hull import certify
from kpstudy.certify.pose_bound_regions import region_pooling, search_regions
from kpstudy.certify.pose_bound_rules import linearised_bound
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.preprocess import to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T
from kpstudy.pose.pnp import solve_pnp
from kpstudy.verify import ConvexHull
from tests.test_campaign import _seed, study  # noqa: F401  (the module fixture)

#: Seconds that only cap a stalled pose-bound search: node budgets decide what it finds.
CAP = 600.0


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


@pytest.mark.slow
def test_certify_records_the_pose_bound_method(study):  # noqa: F811
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    budget = dict(check_samples=0, pose_bound_timeout=CAP, pose_bound_nodes=1)  # the hull
    huge = certify(backbone, vertices, seed, alpha=1e4, **budget)
    assert huge["pb_status"] == "holds" and huge["pb_counterexample"] is None
    assert len(huge["pb_bound"]) == 6 and len(huge["pb_pixels"]) == 23
    assert min(huge["pb_pixels"]) >= 1 and huge["pb_time"] > 0 and huge["pb_stride"] == 1
    small = certify(backbone, vertices, seed, alpha=0.05, **budget)
    if small["pb_stopped"] != "witness":  # a search ran: its regions are the hull's
        assert small["pb_bound"] == huge["pb_bound"]
    else:  # the seed or a first image refuted it: no node was bounded
        assert small["pb_nodes"] == 0 and small["pb_status"] == "violated"
    assert small["pb_status"] in ("violated", "unknown")
    if small["pb_status"] == "violated":  # a two-epoch network: the seed's argmax pose is off
        lam = np.asarray(small["pb_counterexample"])
        assert np.all(lam >= 0) and lam.sum() <= 1 + 1e-12
    with pytest.raises(ValueError, match="^pose_bound_stride"):
        certify(backbone, vertices, seed, pose_bound_timeout=1, pose_bound_stride=2)
    # The regions from zonotope bounds, recorded as such.
    zono = certify(backbone, vertices, seed, alpha=1e4, pose_bound_method="zonotope", **budget)
    assert zono["pb_method"] == "zonotope" and huge["pb_method"] == "forward"
    assert len(zono["pb_pixels"]) == 23 and zono["pb_rule"] in ("enumeration", "linearised")
    # α = 10⁴: every pose PnP gives lies in Ξ, so only a combination whose pose PnP flags
    # as not valid (an infinite error) keeps it open (the tiny network's regions may
    # hold one, depending on its training's thread count).
    if zono["pb_status"] != "holds":
        assert zono["pb_status"] == "unknown" and zono["pb_exact"] == [np.inf] * 6
    assert zono["pb_nodes"] == huge["pb_nodes"] == 1
    with pytest.raises(ValueError, match="^pose_bound_method"):
        certify(backbone, vertices, seed, pose_bound_timeout=1, pose_bound_method="crown")


def test_a_node_budget_gives_the_same_regions_whatever_the_time(study):  # noqa: F811
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    budget = dict(check_samples=0, pose_bound_nodes=3, pose_bound_start_depth=2)
    first = certify(backbone, vertices, seed, alpha=1e4, pose_bound_timeout=CAP, **budget)
    assert 1 <= first["pb_nodes"] <= 3 and first["pb_stopped"] in ("nodes", None)
    assert first["pb_refined"] == 0  # no second search unless asked for
    again = certify(backbone, vertices, seed, alpha=1e4, pose_bound_timeout=300, **budget)
    for key in ("pb_status", "pb_pixels", "pb_bound", "pb_nodes", "pb_stopped"):
        assert again[key] == first[key]


def test_a_counterexample_among_the_first_images_skips_the_search(study):  # noqa: F811
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    # α = 10⁻³: Ξ is so small that the two-epoch network's seed pose already leaves it.
    record = certify(backbone, vertices, seed, alpha=1e-3, check_samples=0, pose_bound_timeout=CAP)
    assert record["pb_status"] == "violated" and record["pb_rule"] == "witness"
    assert record["pb_nodes"] == 0 and record["pb_stopped"] == "witness"
    # No regions, so no bound over them, and no nonlinear check: a witness decided.
    assert record["pb_bound"] is None and record["pb_nonlinear"] is None
    lam = torch.tensor(record["pb_counterexample"], dtype=torch.float64)
    # The seed and the vertices come before the random images: the witness is one of them.
    assert bool(((lam == 0) | (lam == 1)).all()) and lam.sum() <= 1
    s = backbone.input_size
    hull = ConvexHull(to_model_input(vertices, size=s))
    R, t = solve_pnp(seed.points_3d, np.asarray(seed.keypoints, float), seed.K)
    errors = target_pose_errors(backbone, hull.image(lam[None]), seed, R, t)[0]
    assert not np.all(errors <= 1e-3 * np.r_[EPS_R, EPS_T])  # its own pose leaves Ξ


def _block_hull_pose_bound(trained, **search):
    """The study's trained model, its first seed's overlapping m = 2 block hull and the
    :class:`HullPoseBound` on it with ``search``'s settings."""
    data, checkpoint = trained
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
    vertices = hull_vertices(data, seed.image_id, "blocks", 2, True)
    hull = ConvexHull(to_model_input(vertices, size=backbone.input_size))
    R, t = solve_pnp(seed.points_3d, np.asarray(seed.keypoints, float), seed.K)
    pose = pb.HullPoseBound(backbone, hull, seed, R, t, np.zeros((6, 46)), timeout=CAP, **search)
    return backbone, hull, pose


def test_a_refined_search_only_removes_pixels_no_image_reaches(study):  # noqa: F811
    backbone, hull, pose = _block_hull_pose_bound(study, max_nodes=1, refine_nodes=6)
    first, _ = search_regions(backbone, hull, pose.centers, 1, pose.search)
    # Every unreached cell in focus: the second search may split wherever the first left one.
    focus = [np.setdiff1d(p, sorted(w)) for p, w in zip(first.possible, first.witnesses)]
    merged, pixels = pose._refined(first, focus, 6)
    assert 1 < merged.nodes <= first.nodes + 6
    for before, after in zip(first.possible, merged.possible):
        assert set(after.tolist()) <= set(before.tolist())
    lam = torch.cat([hull.sample(256, 0), hull.sample(64, 1, "vertices")]).to(torch.float32)
    with torch.no_grad():
        argmax = argmax_keypoints(backbone(hull.image(lam)))  # (B, K, 2) heatmap (u, v)
    for k, region in enumerate(pixels):
        kept = {tuple(p) for p in region.astype(int).tolist()}
        assert {tuple(p) for p in argmax[:, k].long().tolist()} <= kept


def test_the_search_takes_its_witnesses_from_the_first_images_without_evaluating_them_again(
    study,  # noqa: F811
):
    backbone, hull, pose = _block_hull_pose_bound(study, max_nodes=2)
    alone, _ = search_regions(backbone, hull, pose.centers, 1, pose.search)
    evaluated = []
    hook = backbone.register_forward_hook(lambda m, args, out: evaluated.append(len(args[0])))
    record = pose.decide(np.full(6, 1e6))  # Ξ holds every pose: no early witness
    hook.remove()
    shared, _ = pose._made["search"][0]
    assert record["pb_nodes"] == alone.nodes == shared.nodes
    assert [p.tolist() for p in shared.possible] == [p.tolist() for p in alone.possible]
    assert [sorted(w) for w in shared.witnesses] == [sorted(w) for w in alone.witnesses]
    # The 64 random images once (the search used to draw and evaluate the same 64 again).
    assert 64 <= sum(evaluated) < 2 * 64


def test_at_stride_1_the_proxy_is_the_backbones_own_output():
    """The stride-1 search bounds the backbone itself (its error symbols stay in blocks):
    sound only because the proxy's one-pixel cells are the heatmaps in the backbone's
    own order, checked here with keypoints on the map's edges."""
    from kpstudy.models.cnn import HeatmapCNNPatchDecoder
    from kpstudy.models.proxy import build_proxy

    torch.manual_seed(0)
    net = HeatmapCNNPatchDecoder(5).eval()
    centers = np.array([[0, 0], [63, 0], [0, 63], [63, 63], [20, 41]])
    proxy = build_proxy(net, region_pooling(centers, 1, 64), centers).eval()
    assert proxy.spec.group_sizes == [64 * 64] * 5
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(proxy(x), net(x).flatten(1), rtol=0, atol=0)
