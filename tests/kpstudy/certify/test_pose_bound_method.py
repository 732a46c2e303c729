"""kpstudy.certify.pose_bound_method: certify's pose-bound record on the tiny trained study,
and the exact decision (issue 27, part 2): PnP over every combination of region pixels
decides where there are few enough, the linearised bound only above that. The method's
seams (the region search, the enumeration, the attack, its limits) are patched where it
looks them up, in :mod:`kpstudy.certify.pose_bound_method`; the parts' own code is tested
in test_pose_bound_regions.py, test_pose_bound_rules.py and test_pose_bound_attack.py."""

import itertools
import types

import numpy as np
import pytest
import torch

from data_gen.perturb import hull_vertices
from kpstudy.certify import pose_bound_method as pb
from kpstudy.certify import pose_bound_regions as pb_regions
from kpstudy.certify import pose_bound_rules as rules
from kpstudy.certify.allocation_method import target_pose_errors
from kpstudy.certify.hull import certify
from kpstudy.certify.pose_bound_regions import search_regions
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.pooling import num_cells
from kpstudy.models.preprocess import to_image_pixels, to_model_input
from kpstudy.models.training import load_checkpoint
from kpstudy.pose.geometry import EPS_R, EPS_T, euler_from_matrix, wrap_degrees
from kpstudy.pose.pnp import solve_pnp, solve_pnp_batch
from kpstudy.verify import ConvexHull, Regions
from tests.conftest import seed_image
from tests.helpers.pose_bound import HM, Peaks, Ramp, far_tolerance, regions_with, unit_hull


@pytest.fixture
def attacks(monkeypatch):
    """The targets of every :func:`pb.targeted_witness` call, in order."""
    calls, real = [], pb.targeted_witness

    def counted(backbone, hull, targets, starts, **kw):
        calls.append(np.asarray(targets))
        return real(backbone, hull, targets, starts, **kw)

    monkeypatch.setattr(pb, "targeted_witness", counted)
    return calls


def _with_regions(monkeypatch, pixels, witnesses=()):
    """Make the reachability search return ``pixels`` (heatmap ``(u, v)`` per keypoint)."""
    regions = types.SimpleNamespace(
        witnesses=list(witnesses), nodes=1, complete=True, stats={"stopped": None}
    )
    pixels = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in pixels]
    monkeypatch.setattr(pb, "search_regions", lambda *args, **kwargs: (regions, pixels))


def _brute_force(seed, positions, R, t):
    """The largest pose error per axis, one OpenCV PnP per combination."""
    worst = np.zeros(6)
    for combination in itertools.product(*positions):
        pose = solve_pnp(seed.points_3d, np.array(combination), seed.K, init=(R, t))
        if not pose.valid:
            return np.full(6, np.inf)
        dr = wrap_degrees(euler_from_matrix(pose.R) - euler_from_matrix(R))
        worst = np.maximum(worst, np.abs(np.r_[dr, pose.t - t]))
    return worst


def _decide(scene, M, eps, kappa=1.0, backbone=None):
    seed, R, t, _, centers = scene
    backbone = Peaks(centers) if backbone is None else backbone
    return pb.pose_bound(backbone, unit_hull(), seed, R, t, M, eps, kappa=kappa, random_corners=4)


def test_enumeration_proves_what_the_linearised_bound_leaves_open(scene, monkeypatch):
    seed, R, t, factors, centers = scene
    pixels = regions_with(centers, [(0, (1, 0)), (5, (0, 1)), (9, (-1, -1))])
    _with_regions(monkeypatch, pixels)
    exact = _brute_force(seed, [to_image_pixels(np.array(p), factors) for p in pixels], R, t)
    eps = 1.5 * exact + 1e-6
    M = np.full((6, 46), 1.0)  # a linearisation far off: bound ≫ ε
    record = _decide(scene, M, eps)
    assert np.any(np.asarray(record["pb_bound"]) > eps)  # the linearised rule: unknown
    assert record["pb_status"] == "holds" and record["pb_rule"] == "enumeration"
    assert record["pb_combinations"] == 8 and record["pb_counterexample"] is None
    np.testing.assert_allclose(record["pb_exact"], exact, rtol=1e-5, atol=1e-7)
    # κ is the linearisation's margin: the exact decision is the same whatever κ, ...
    strict = _decide(scene, M, eps, kappa=2.0)
    assert strict["pb_status"] == "holds" and strict["pb_rule"] == "enumeration"
    # ... and it holds up to Ξ's edge, not beyond: ε just below the exact error is open.
    edge = _decide(scene, M, exact + 1e-6)
    assert edge["pb_status"] == "holds"
    axis = int(np.argmax(exact))
    below = exact + 1e-6
    below[axis] = exact[axis] * (1 - 1e-3)
    assert _decide(scene, M, below)["pb_status"] == "unknown"


def test_the_cells_of_one_hull_share_its_search_and_enumeration(scene, monkeypatch):
    seed, R, t, factors, centers = scene
    pixels = regions_with(centers, [(0, (1, 0)), (5, (0, 1))])
    _with_regions(monkeypatch, pixels)
    searches, enumerations = [], []
    search, enumerate_ = pb.search_regions, pb.enumerate_combinations
    monkeypatch.setattr(pb, "search_regions", lambda *a, **k: searches.append(1) or search(*a, **k))
    monkeypatch.setattr(
        pb, "enumerate_combinations", lambda *a: enumerations.append(1) or enumerate_(*a)
    )
    exact = _brute_force(seed, [to_image_pixels(np.array(p), factors) for p in pixels], R, t)
    M = np.full((6, 46), 1.0)
    cells = [(1.5 * exact + 1e-6, 1.0), (1.5 * exact + 1e-6, 2.0), (1.2 * exact + 1e-6, 1.0)]
    hull = pb.HullPoseBound(Peaks(centers), unit_hull(), seed, R, t, M, random_corners=4)
    records = [hull.decide(eps, kappa) for eps, kappa in cells]
    assert len(searches) == 1 and len(enumerations) == 2  # one per distinct Ξ
    assert [r["pb_status"] for r in records] == ["holds"] * 3
    for (eps, kappa), record in zip(cells, records):  # as if each cell ran alone
        alone = _decide(scene, M, eps, kappa)
        for key in ("pb_status", "pb_rule", "pb_exact", "pb_bound", "pb_pixels"):
            assert record[key] == alone[key]


def test_a_combination_outside_the_tolerance_is_never_a_holds(scene, monkeypatch):
    centers = scene[-1]
    eps, axis = far_tolerance(scene)
    _with_regions(monkeypatch, regions_with(centers, [(0, (8, 0))]))
    M = np.zeros((6, 46))  # a linearisation that says nothing moves: bound 0, 'holds'
    record = _decide(scene, M, eps)
    assert record["pb_bound"] == [0.0] * 6
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    assert record["pb_exact"][axis] > eps[axis]
    # The same pixel reached by a witness image (λ = 1: its argmax moves there) refutes.
    moved = centers.copy()
    moved[0] += [8, 0]
    witnesses = [{0: torch.tensor([1.0], dtype=torch.float64)}]
    _with_regions(monkeypatch, regions_with(centers, [(0, (8, 0))]), witnesses)
    refuted = _decide(scene, M, eps, backbone=Peaks(centers, moved))
    assert refuted["pb_status"] == "violated" and refuted["pb_rule"] == "witness"
    # Found among the first images (the hull's vertex or a random image past λ = 0.5).
    assert refuted["pb_counterexample"][0] > 0.5 and refuted["pb_exact"] is None


def test_an_enumerated_combination_outside_the_tolerance_is_sought_in_the_hull(scene, monkeypatch):
    centers = scene[-1]
    eps, _ = far_tolerance(scene)
    _with_regions(monkeypatch, regions_with(centers, [(0, (8, 0))]))
    # Only the seed among the first images, and no witness from the search: the combination
    # with keypoint 0 moved (outside Ξ) is left to the targeted search.
    monkeypatch.setattr(pb, "_first_points", lambda hull, seed: [torch.zeros(1).double()])
    moved = centers.copy()
    moved[0] += [8, 0]
    gain = np.where(np.arange(len(centers)) == 0, 1.0, 0.0)  # only keypoint 0 moves (b > 0.5)
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=Ramp(centers, moved, gain))
    assert record["pb_status"] == "violated" and record["pb_rule"] == "witness"
    assert record["pb_counterexample"][0] > 0.5


def test_a_one_keypoint_move_is_sought_when_the_farthest_combination_is_no_image(
    scene, monkeypatch, attacks
):
    seed, R, t, factors, centers = scene
    eps, _ = far_tolerance(scene)
    # Keypoint 0 can go 8 px right (outside Ξ) and keypoint 1 one pixel down; the model moves
    # keypoint 0 alone, so the farthest combination (if it moves keypoint 1 too) is no image.
    _with_regions(monkeypatch, regions_with(centers, [(0, (8, 0)), (1, (0, 1))]))
    monkeypatch.setattr(pb, "_first_points", lambda hull, seed: [torch.zeros(1).double()])
    moved = centers.copy()
    moved[0] += [8, 0]
    gain = np.where(np.arange(len(centers)) == 0, 1.0, 0.0)
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=Ramp(centers, moved, gain))
    assert record["pb_status"] == "violated" and record["pb_rule"] == "witness"
    assert record["pb_counterexample"][0] > 0.5
    # A model whose keypoint 0 never moves leaves it open: the attack proves nothing.
    never = np.zeros(len(centers))
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=Ramp(centers, moved, never))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    # Above the enumeration limit no move is sought (the regions are the bounds' slack).
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)
    sought = len(attacks)
    record = _decide(scene, np.full((6, 46), 1.0), eps, backbone=Ramp(centers, moved, gain))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "linearised"
    assert len(attacks) == sought


def test_a_pose_that_pnp_flags_is_outside(scene, monkeypatch):
    real = solve_pnp_batch

    def flag_the_moved_one(P, V, K, init, **kw):
        pose = real(P, V, K, init, **kw)
        pose.valid = pose.valid & (np.abs(V[:, 0] - V[0, 0]).max(-1) < 1e-9)
        return pose

    _, _, _, _, centers = scene
    _with_regions(monkeypatch, regions_with(centers, [(0, (1, 0))]))
    monkeypatch.setattr(rules, "solve_pnp_batch", flag_the_moved_one)
    record = _decide(scene, np.zeros((6, 46)), np.full(6, 1e3))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    assert record["pb_exact"] == [np.inf] * 6


def test_above_the_limit_the_linearised_bound_decides(scene, monkeypatch):
    centers = scene[-1]
    eps, _ = far_tolerance(scene)  # enumerated, the far combination leaves it open
    _with_regions(monkeypatch, regions_with(centers, [(0, (8, 0))]))
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)
    record = _decide(scene, np.zeros((6, 46)), eps)
    assert record["pb_status"] == "holds" and record["pb_rule"] == "linearised"
    assert record["pb_combinations"] == 2 and record["pb_exact"] is None
    open_ = _decide(scene, np.full((6, 46), 1.0), eps)
    assert open_["pb_status"] == "unknown" and open_["pb_rule"] == "linearised"
    # The default limit: 5²³ combinations are not enumerated, and are recorded as a float.
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 10**6)
    offsets = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    _with_regions(monkeypatch, regions_with(centers, [(k, o) for k in range(23) for o in offsets]))
    huge = _decide(scene, np.zeros((6, 46)), eps)
    assert huge["pb_status"] == "holds" and huge["pb_rule"] == "linearised"
    assert huge["pb_combinations"] == float(5**23) and isinstance(huge["pb_combinations"], float)
    assert huge["pb_exact"] is None


@pytest.mark.parametrize("chunk", [1, 5, 10**5])
def test_enumeration_equals_a_brute_force_loop(scene, monkeypatch, chunk):
    seed, R, t, factors, centers = scene
    rng = np.random.default_rng(chunk)
    moves = [(k, tuple(rng.integers(-3, 4, 2))) for k in (2, 2, 7, 11, 11, 20)]
    pixels = regions_with(centers, moves)  # 3 · 2 · 3 · 2 = 36 combinations (or fewer)
    positions = [to_image_pixels(np.unique(np.array(p), axis=0), factors) for p in pixels]
    brute = _brute_force(seed, positions, R, t)
    sizes = []
    real = solve_pnp_batch

    def counted(P, V, K, init, **kw):
        sizes.append(len(V))
        np.testing.assert_array_equal(init[0], np.broadcast_to(R, (len(V), 3, 3)))
        np.testing.assert_array_equal(init[1], np.broadcast_to(t, (len(V), 3)))
        return real(P, V, K, init, **kw)

    monkeypatch.setattr(rules, "solve_pnp_batch", counted)
    exact = rules.enumerated_pose_error(seed, positions, R, t, chunk=chunk)
    total = int(np.prod([len(p) for p in positions]))
    assert sum(sizes) == total and max(sizes) <= chunk
    np.testing.assert_allclose(exact, brute, rtol=1e-5, atol=1e-7)
    # Through pose_bound, in chunks of the module's size.
    monkeypatch.setattr(rules, "ENUMERATION_CHUNK", chunk)
    _with_regions(monkeypatch, [np.unique(np.array(p), axis=0) for p in pixels])
    record = _decide(scene, np.zeros((6, 46)), 2 * brute + 1e-6)
    assert record["pb_combinations"] == total and record["pb_rule"] == "enumeration"
    np.testing.assert_allclose(record["pb_exact"], brute, rtol=1e-5, atol=1e-7)


def _stride1_cells(scene):
    """The scene's rounded centres (int), their stride-1 pooling, the cell index of
    keypoint k's heatmap pixel ``(u, v)``, and the pixel 8 right of keypoint 0's."""
    centers = scene[-1].astype(np.int64)
    pooling = pb_regions.region_pooling(centers, 1, HM)
    n_h = [num_cells(horizontal, HM) for horizontal, _ in pooling]

    def cell(k, u, v):
        return int(v * n_h[k] + u)  # stride 1: one pixel a cell

    return centers, pooling, cell, centers[0] + [8, 0]


def test_the_refinement_aims_at_unreached_cells_of_combinations_outside_the_tolerance(scene):
    seed, R, t, factors, _ = scene
    eps, _ = far_tolerance(scene)
    centers, pooling, cell, far = _stride1_cells(scene)
    possible = [np.array([cell(k, *c)]) for k, c in enumerate(centers)]
    possible[0] = np.array(sorted([cell(0, *centers[0]), cell(0, *far)]))
    # The seed reaches every keypoint's rounded pixel (a witness at λ = 0).
    seed_lam = torch.zeros(1, dtype=torch.float64)
    witnesses = [{cell(k, *c): seed_lam} for k, c in enumerate(centers)]
    regions = types.SimpleNamespace(possible=possible, witnesses=witnesses)
    pixels = pb_regions.region_pixels(regions, pooling, HM)
    assert pixels[0].tolist() == [centers[0].tolist(), far.tolist()]
    # Only the combination with keypoint 0 at ``far`` leaves Ξ; every pixel in it is involved.
    positions = [to_image_pixels(p, factors) for p in pixels]
    _, farthest, involved = rules.enumerate_combinations(seed, positions, R, t, eps)
    assert involved[0].tolist() == [False, True] and all(m.all() for m in involved[1:])
    assert farthest.tolist() == [1] + [0] * (len(centers) - 1)
    # Of those, only ``far`` has no witness: the one cell a split may remove.
    focus = pb_regions.focus_cells(regions, pooling, HM, involved)
    assert focus[0].tolist() == [cell(0, *far)] and not any(len(f) for f in focus[1:])
    # A cell some image is known to reach is a fact, not a split's target.
    regions.witnesses[0][cell(0, *far)] = torch.ones(1, dtype=torch.float64)
    assert not any(len(f) for f in pb_regions.focus_cells(regions, pooling, HM, involved))


def test_under_the_linearised_rule_the_refinement_aims_at_single_moves_outside(scene, monkeypatch):
    seed, R, t, factors, _ = scene
    eps, _ = far_tolerance(scene)
    centers, pooling, cell, far = _stride1_cells(scene)
    pose = pb.HullPoseBound(Peaks(centers), unit_hull(), seed, R, t, np.zeros((6, 46)))
    pose._spent = 0.0
    # Keypoint 0 may go 8 pixels right (alone, outside Ξ), keypoint 1 one pixel (inside).
    near = centers[1] + [1, 0]
    possible = [np.array([cell(k, *c)]) for k, c in enumerate(centers)]
    possible[0] = np.array(sorted([cell(0, *centers[0]), cell(0, *far)]))
    possible[1] = np.array(sorted([cell(1, *centers[1]), cell(1, *near)]))
    seed_lam = torch.zeros(1, dtype=torch.float64)
    witnesses = [{cell(k, *c): seed_lam} for k, c in enumerate(centers)]
    regions = types.SimpleNamespace(possible=possible, witnesses=witnesses)
    pixels = pb_regions.region_pixels(regions, pooling, HM)
    verdict = {"rule": "linearised", "involved": None}
    focus = pose._refine_focus(eps, verdict, regions, pixels, budget=1)
    assert focus[0].tolist() == [cell(0, *far)] and not any(len(f) for f in focus[1:])
    # More cells than FOCUS_PER_NODE per node of the budget: no search.
    monkeypatch.setattr(pb, "FOCUS_PER_NODE", 0)
    assert pose._refine_focus(eps, verdict, regions, pixels, budget=1) is None
    # Nothing outside alone: nothing to aim at.
    monkeypatch.setattr(pb, "FOCUS_PER_NODE", 8)
    assert pose._refine_focus(2 * eps + 100, verdict, regions, pixels, budget=1) is None


def _far_pixel_search(scene, foci, nodes=(1, 1), stopped=(None, None)):
    """A fake ``search_regions``: the first search (``nodes[0]`` nodes, stopping on
    ``stopped[0]``) leaves keypoint 0's far pixel possible, a focused one (``nodes[1]``,
    ``stopped[1]``) removes it; each call's focus is appended to ``foci``."""
    centers, pooling, cell, far = _stride1_cells(scene)
    seed_lam = torch.zeros(1, dtype=torch.float64)

    def search(backbone, hull, centers_, stride, search, focus=None, resume=None, witnesses=None):
        foci.append(focus)
        first = focus is None
        possible = [np.array([cell(k, *c)]) for k, c in enumerate(centers)]
        if first:
            possible[0] = np.array(sorted([cell(0, *centers[0]), cell(0, *far)]))
        witnesses = [{cell(k, *c): seed_lam} for k, c in enumerate(centers)]
        stats = {"stopped": stopped[0] if first else stopped[1]}
        found = Regions(
            [HM * HM] * len(centers), possible, witnesses, 0.0, nodes[0 if first else 1], stats
        )
        return found, pb_regions.region_pixels(found, pooling, HM)

    return search


def test_a_linearised_unknown_gets_a_focused_round_that_may_decide_it(scene, monkeypatch):
    seed, R, t, factors, _ = scene
    eps, _ = far_tolerance(scene)
    centers, _, cell, far = _stride1_cells(scene)
    foci = []
    monkeypatch.setattr(pb, "search_regions", _far_pixel_search(scene, foci, nodes=(2, 1)))
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)  # 2 combinations: the linearised rule
    M = np.full((6, 46), 1e3)  # far off: the linearised bound leaves it open
    args = (Peaks(centers), unit_hull(), seed, R, t, M, eps)
    alone = pb.pose_bound(*args, random_corners=4)
    assert alone["pb_status"] == "unknown" and alone["pb_rule"] == "linearised"
    assert alone["pb_refined"] == 0 and len(foci) == 1
    refined = pb.pose_bound(*args, random_corners=4, refine_nodes=4)
    assert foci[2][0].tolist() == [cell(0, *far)] and not any(len(f) for f in foci[2][1:])
    assert refined["pb_status"] == "holds" and refined["pb_rule"] == "enumeration"
    assert refined["pb_refined"] == 1 and refined["pb_nodes"] == 3
    assert refined["pb_pixels"] == [1] * len(centers)


@pytest.mark.parametrize(
    "first, refinement, expected",
    [
        ("time", "nodes", "time"),
        ("time", None, "time"),
        ("nodes", "time", "time"),
        ("nodes", "nodes", "nodes"),
    ],
)
def test_a_time_cap_on_any_of_the_searches_a_cell_used_is_in_its_record(
    scene, monkeypatch, first, refinement, expected
):
    """Issue 62, part 3: ``pb_stopped`` is ``'time'`` when the time cap ended the first
    search or a focused round, whichever stopped last, in every cell whose regions came
    from that search (also a cell that reuses the hull's shared searches); a cell decided
    by the first search alone reports that one's. The searches are faked: no timing."""
    seed, R, t, factors, _ = scene
    eps, _ = far_tolerance(scene)
    centers, *_ = _stride1_cells(scene)
    foci = []
    search = _far_pixel_search(scene, foci, stopped=(first, refinement))
    monkeypatch.setattr(pb, "search_regions", search)
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)  # 2 combinations: the linearised rule
    M = np.full((6, 46), 1e3)  # far off: the linearised bound leaves the tight Ξ open
    loose = np.full(6, 1e9)  # ... and not this one: no focused round
    args = (Peaks(centers), unit_hull(), seed, R, t, M)
    alone = pb.pose_bound(*args, eps, random_corners=4, refine_nodes=4)
    assert [f is None for f in foci] == [True, False] and alone["pb_refined"] == 1
    assert alone["pb_status"] == "holds" and alone["pb_stopped"] == expected
    foci.clear()
    hull = pb.HullPoseBound(*args, random_corners=4, refine_nodes=4)
    records = [hull.decide(e) for e in (eps, loose, eps)]
    assert [f is None for f in foci] == [True, False]  # the third cell reuses both searches
    assert [r["pb_refined"] for r in records] == [1, 0, 1]
    assert [r["pb_status"] for r in records] == ["holds"] * 3
    assert [r["pb_stopped"] for r in records] == [expected, first, expected]


def test_the_start_depth_grows_with_the_hulls_perturbed_images(scene):
    """``start_splits`` adds ⌈start_splits · n⌉ splits for a hull of n perturbed images (at
    most MAX_START_DEPTH); a negative or non-numeric value is refused by name."""
    from kpstudy.verify.reachable import MAX_START_DEPTH

    seed, R, t, _, _ = scene
    centers, *_ = _stride1_cells(scene)
    images = torch.rand(5, 1, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    M = np.zeros((6, 46))
    for n, splits, depth in [(1, 1.5, 3), (3, 1.5, 6), (4, 1.75, 8), (4, 12.0, MAX_START_DEPTH)]:
        hull = ConvexHull(images[: n + 1])
        pose = pb.HullPoseBound(
            Peaks(centers), hull, seed, R, t, M, start_depth=1, start_splits=splits
        )
        assert pose.search["start_depth"] == depth
    for bad in (-0.5, "2", True):
        with pytest.raises(ValueError, match="^start_splits"):
            pb.HullPoseBound(Peaks(centers), unit_hull(), seed, R, t, M, start_splits=bad)


#: Seconds that only cap a stalled pose-bound search: node budgets decide what it finds.
CAP = 600.0


@pytest.mark.slow
def test_certify_records_the_pose_bound_method(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
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


def test_a_node_budget_gives_the_same_regions_whatever_the_time(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
    vertices = hull_vertices(data, seed.image_id, "brightness", level=2.0)
    budget = dict(check_samples=0, pose_bound_nodes=3, pose_bound_start_depth=2)
    first = certify(backbone, vertices, seed, alpha=1e4, pose_bound_timeout=CAP, **budget)
    assert 1 <= first["pb_nodes"] <= 3 and first["pb_stopped"] in ("nodes", None)
    assert first["pb_refined"] == 0  # no second search unless asked for
    again = certify(backbone, vertices, seed, alpha=1e4, pose_bound_timeout=300, **budget)
    for key in ("pb_status", "pb_pixels", "pb_bound", "pb_nodes", "pb_stopped"):
        assert again[key] == first[key]


def test_a_counterexample_among_the_first_images_skips_the_search(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = seed_image(data)
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
    seed = seed_image(data)
    vertices = hull_vertices(data, seed.image_id, "blocks", 2, True)
    hull = ConvexHull(to_model_input(vertices, size=backbone.input_size))
    R, t = solve_pnp(seed.points_3d, np.asarray(seed.keypoints, float), seed.K)
    pose = pb.HullPoseBound(backbone, hull, seed, R, t, np.zeros((6, 46)), timeout=CAP, **search)
    return backbone, hull, pose


def test_a_refined_search_only_removes_pixels_no_image_reaches(study):
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
    study,
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
