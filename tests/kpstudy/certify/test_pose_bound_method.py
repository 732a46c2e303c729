"""kpstudy.certify.pose_bound_method's exact decision (issue 27, part 2): PnP over every
combination of region pixels decides where there are few enough, the linearised bound only
above that, and the tables count which rule decided. The method's seams (the region search,
the enumeration, the attack, its limits) are patched where it looks them up, in
:mod:`kpstudy.certify.pose_bound_method`; the parts' own code in
:mod:`~kpstudy.certify.pose_bound_regions`, :mod:`~kpstudy.certify.pose_bound_rules` and
:mod:`~kpstudy.certify.pose_bound_attack`."""

import io
import itertools
import types

import numpy as np
import pandas as pd
import pytest
import torch
from torch import nn

from kpstudy.certify import pose_bound_attack as attack
from kpstudy.certify import pose_bound_method as pb
from kpstudy.certify import pose_bound_regions as pb_regions
from kpstudy.certify import pose_bound_rules as rules
from kpstudy.certify.allocation_method import SeedImage
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.pooling import num_cells
from kpstudy.models.preprocess import scale_factors, to_image_pixels, to_input_pixels
from kpstudy.pose.geometry import euler_from_matrix, wrap_degrees
from kpstudy.pose.pnp import solve_pnp, solve_pnp_batch
from kpstudy.study import tables
from kpstudy.verify import ConvexHull, Regions
from tests.conftest import IMAGE_SIZE, views

HM = 64  # heatmap side


class _Peaks(nn.Module):
    """A backbone whose heatmaps peak at fixed pixels ``(K, 2)`` (u, v), and at ``moved``
    instead for images brighter than 0.5 (the hull's second vertex)."""

    heatmap_size = input_size = HM

    def __init__(self, peaks, moved=None):
        super().__init__()
        self.peaks = np.asarray(peaks, dtype=np.int64)
        self.moved = self.peaks if moved is None else np.asarray(moved, dtype=np.int64)

    def forward(self, x):
        out = torch.zeros(len(x), len(self.peaks), HM, HM)
        for b, image in enumerate(x):
            peaks = self.moved if image.mean() > 0.5 else self.peaks
            for k, (u, v) in enumerate(peaks):
                out[b, k, v, u] = 1.0
        return out


class _Ramp(nn.Module):
    """A differentiable backbone: keypoint k's heatmap is ``1 − b`` at ``peaks[k]`` and
    ``b·gain[k]`` at ``moved[k]`` (0 elsewhere), ``b`` the image's mean brightness."""

    heatmap_size = input_size = HM

    def __init__(self, peaks, moved, gain):
        super().__init__()
        self.peaks, self.moved = (np.asarray(p).astype(np.int64) for p in (peaks, moved))
        self.gain = torch.as_tensor(gain, dtype=torch.float32)

    def forward(self, x):
        b = x.flatten(1).mean(1)[:, None]  # (B, 1)
        out = x.new_zeros(len(x), len(self.peaks), HM * HM)
        index = lambda p: torch.as_tensor(p[:, 1] * HM + p[:, 0])[None, :, None]  # noqa: E731
        K = len(self.peaks)
        out = out.scatter_add(
            2, index(self.peaks).expand(len(x), -1, 1), (1 - b).expand(-1, K)[..., None]
        )
        moved = (b * self.gain.to(x.dtype)).expand(-1, K)[..., None]
        out = out.scatter_add(2, index(self.moved).expand(len(x), -1, 1), moved)
        return out.view(len(x), -1, HM, HM)


def test_the_targeted_witness_reaches_joint_combinations_and_only_those():
    peaks = np.array([[10, 10], [20, 20], [30, 30]])
    moved = peaks + [1, 0]
    # Keypoint k moves once b·gain_k > 1 − b: at b > 1/(1 + gain_k) = 0.75, 0.5, 0.25.
    model = _Ramp(peaks, moved, [1 / 3, 1.0, 3.0])
    hull = _hull()
    seed = [torch.zeros(1, dtype=torch.float64)]
    lam = attack.targeted_witness(model, hull, moved, seed)
    assert lam is not None and lam.item() > 0.75
    heat = model(hull.image(lam[None], dtype=torch.float32))
    assert np.array_equal(argmax_keypoints(heat)[0].numpy(), moved)
    # Keypoint 0 at its peak (b < 0.75) with keypoint 1 moved (b > 0.5): reachable.
    both = np.stack([peaks[0], moved[1], moved[2]])
    assert 0.5 < attack.targeted_witness(model, hull, both, seed).item() < 0.75
    # Keypoint 1 at its peak (b < 0.5) with keypoint 0 moved (b > 0.75): no image does it.
    assert (
        attack.targeted_witness(model, hull, np.stack([moved[0], peaks[1], moved[2]]), seed) is None
    )


def test_a_free_keypoint_and_alternative_targets():
    peaks = np.array([[10, 10], [20, 20], [30, 30]])
    moved = peaks + [1, 0]
    model = _Ramp(peaks, moved, [1 / 3, 1.0, 3.0])
    hull, seed = _hull(), [torch.zeros(1, dtype=torch.float64)]
    # Keypoint 0 moved with keypoint 1 at its peak is no image's argmax; keypoint 0 moved
    # with keypoint 1 free is (b > 0.75).
    unreachable = np.stack([moved[0], peaks[1], moved[2]])
    assert attack.targeted_witness(model, hull, unreachable, seed) is None
    free = unreachable.copy()
    free[1:] = -1
    assert attack.targeted_witness(model, hull, free, seed).item() > 0.75
    # Several targets at once: the first reached is returned.
    lam = attack.targeted_witness(model, hull, np.stack([unreachable, free]), seed)
    assert lam is not None and lam.item() > 0.75
    with pytest.raises(ValueError, match="targets: expected shape"):
        attack.targeted_witness(model, hull, np.zeros(2, dtype=np.int64), seed)


@pytest.fixture(scope="module")
def scene(P, K):
    """A seed image (exact keypoints), its nominal pose and the rounded heatmap pixels."""
    R, t, V = views(1, 3, K, P)
    seed = SeedImage(0, V[0], K, P, IMAGE_SIZE)
    factors = scale_factors(IMAGE_SIZE, HM)
    centers = np.clip(np.rint(to_input_pixels(V[0], factors)), 0, HM - 1)
    return seed, R[0], t[0], factors, centers


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


def _hull():
    return ConvexHull(torch.stack([torch.zeros(1, 2, 2), torch.ones(1, 2, 2)]))


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


def _regions_with(centers, moves):
    """Each keypoint's rounded pixel, plus the pixels ``centers[k] + offset`` of ``moves``."""
    pixels = [[c] for c in centers]
    for k, offset in moves:
        pixels[k].append(centers[k] + np.asarray(offset))
    return pixels


def _decide(scene, M, eps, kappa=1.0, backbone=None):
    seed, R, t, _, centers = scene
    backbone = _Peaks(centers) if backbone is None else backbone
    return pb.pose_bound(backbone, _hull(), seed, R, t, M, eps, kappa=kappa, random_corners=4)


def test_enumeration_proves_what_the_linearised_bound_leaves_open(scene, monkeypatch):
    seed, R, t, factors, centers = scene
    pixels = _regions_with(centers, [(0, (1, 0)), (5, (0, 1)), (9, (-1, -1))])
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
    pixels = _regions_with(centers, [(0, (1, 0)), (5, (0, 1))])
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
    hull = pb.HullPoseBound(_Peaks(centers), _hull(), seed, R, t, M, random_corners=4)
    records = [hull.decide(eps, kappa) for eps, kappa in cells]
    assert len(searches) == 1 and len(enumerations) == 2  # one per distinct Ξ
    assert [r["pb_status"] for r in records] == ["holds"] * 3
    for (eps, kappa), record in zip(cells, records):  # as if each cell ran alone
        alone = _decide(scene, M, eps, kappa)
        for key in ("pb_status", "pb_rule", "pb_exact", "pb_bound", "pb_pixels"):
            assert record[key] == alone[key]


def _far_tolerance(scene):
    """Ξ that holds the seed's rounded pixels' pose but not the pose with keypoint 0 moved
    by 8 heatmap pixels (on one axis), and the index of that axis."""
    seed, R, t, factors, centers = scene
    near = [to_image_pixels(c[None], factors) for c in centers]
    far = list(near)
    far[0] = to_image_pixels(centers[0][None] + [8, 0], factors)
    e_near = rules.enumerated_pose_error(seed, near, R, t)
    e_far = rules.enumerated_pose_error(seed, far, R, t)
    axis = int(np.argmax(e_far / e_near))
    assert e_far[axis] > 2 * e_near[axis]
    eps = 2 * np.maximum(e_near, e_far)
    eps[axis] = 0.5 * (e_near[axis] + e_far[axis])
    return eps, axis


def test_a_combination_outside_the_tolerance_is_never_a_holds(scene, monkeypatch):
    centers = scene[-1]
    eps, axis = _far_tolerance(scene)
    _with_regions(monkeypatch, _regions_with(centers, [(0, (8, 0))]))
    M = np.zeros((6, 46))  # a linearisation that says nothing moves: bound 0, 'holds'
    record = _decide(scene, M, eps)
    assert record["pb_bound"] == [0.0] * 6
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    assert record["pb_exact"][axis] > eps[axis]
    # The same pixel reached by a witness image (λ = 1: its argmax moves there) refutes.
    moved = centers.copy()
    moved[0] += [8, 0]
    witnesses = [{0: torch.tensor([1.0], dtype=torch.float64)}]
    _with_regions(monkeypatch, _regions_with(centers, [(0, (8, 0))]), witnesses)
    refuted = _decide(scene, M, eps, backbone=_Peaks(centers, moved))
    assert refuted["pb_status"] == "violated" and refuted["pb_rule"] == "witness"
    # Found among the first images (the hull's vertex or a random image past λ = 0.5).
    assert refuted["pb_counterexample"][0] > 0.5 and refuted["pb_exact"] is None


def test_an_enumerated_combination_outside_the_tolerance_is_sought_in_the_hull(scene, monkeypatch):
    centers = scene[-1]
    eps, _ = _far_tolerance(scene)
    _with_regions(monkeypatch, _regions_with(centers, [(0, (8, 0))]))
    # Only the seed among the first images, and no witness from the search: the combination
    # with keypoint 0 moved (outside Ξ) is left to the targeted search.
    monkeypatch.setattr(pb, "_first_points", lambda hull, seed: [torch.zeros(1).double()])
    moved = centers.copy()
    moved[0] += [8, 0]
    gain = np.where(np.arange(len(centers)) == 0, 1.0, 0.0)  # only keypoint 0 moves (b > 0.5)
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=_Ramp(centers, moved, gain))
    assert record["pb_status"] == "violated" and record["pb_rule"] == "witness"
    assert record["pb_counterexample"][0] > 0.5


def test_single_moves_are_the_possible_pixels_that_alone_leave_the_tolerance(scene):
    seed, R, t, factors, centers = scene
    eps, _ = _far_tolerance(scene)
    pixels = _regions_with(centers, [(0, (8, 0)), (0, (1, 0)), (3, (0, 1))])
    moves = rules.single_moves(
        seed, [np.asarray(p, float) for p in pixels], centers, factors, R, t, eps
    )
    assert [(k, tuple(p)) for k, p in moves] == [(0, tuple(centers[0] + [8, 0]))]
    wide = np.full(6, 1e6)
    assert (
        rules.single_moves(
            seed, [np.asarray(p, float) for p in pixels], centers, factors, R, t, wide
        )
        == []
    )


def test_a_one_keypoint_move_is_sought_when_the_farthest_combination_is_no_image(
    scene, monkeypatch, attacks
):
    seed, R, t, factors, centers = scene
    eps, _ = _far_tolerance(scene)
    # Keypoint 0 can go 8 px right (outside Ξ) and keypoint 1 one pixel down; the model moves
    # keypoint 0 alone, so the farthest combination (if it moves keypoint 1 too) is no image.
    _with_regions(monkeypatch, _regions_with(centers, [(0, (8, 0)), (1, (0, 1))]))
    monkeypatch.setattr(pb, "_first_points", lambda hull, seed: [torch.zeros(1).double()])
    moved = centers.copy()
    moved[0] += [8, 0]
    gain = np.where(np.arange(len(centers)) == 0, 1.0, 0.0)
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=_Ramp(centers, moved, gain))
    assert record["pb_status"] == "violated" and record["pb_rule"] == "witness"
    assert record["pb_counterexample"][0] > 0.5
    # A model whose keypoint 0 never moves leaves it open: the attack proves nothing.
    never = np.zeros(len(centers))
    record = _decide(scene, np.zeros((6, 46)), eps, backbone=_Ramp(centers, moved, never))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    # Above the enumeration limit no move is sought (the regions are the bounds' slack).
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)
    sought = len(attacks)
    record = _decide(scene, np.full((6, 46), 1.0), eps, backbone=_Ramp(centers, moved, gain))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "linearised"
    assert len(attacks) == sought


def test_a_pose_that_pnp_flags_is_outside(scene, monkeypatch):
    real = solve_pnp_batch

    def flag_the_moved_one(P, V, K, init, **kw):
        pose = real(P, V, K, init, **kw)
        pose.valid = pose.valid & (np.abs(V[:, 0] - V[0, 0]).max(-1) < 1e-9)
        return pose

    _, _, _, _, centers = scene
    _with_regions(monkeypatch, _regions_with(centers, [(0, (1, 0))]))
    monkeypatch.setattr(rules, "solve_pnp_batch", flag_the_moved_one)
    record = _decide(scene, np.zeros((6, 46)), np.full(6, 1e3))
    assert record["pb_status"] == "unknown" and record["pb_rule"] == "enumeration"
    assert record["pb_exact"] == [np.inf] * 6


def test_above_the_limit_the_linearised_bound_decides(scene, monkeypatch):
    centers = scene[-1]
    eps, _ = _far_tolerance(scene)  # enumerated, the far combination leaves it open
    _with_regions(monkeypatch, _regions_with(centers, [(0, (8, 0))]))
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)
    record = _decide(scene, np.zeros((6, 46)), eps)
    assert record["pb_status"] == "holds" and record["pb_rule"] == "linearised"
    assert record["pb_combinations"] == 2 and record["pb_exact"] is None
    open_ = _decide(scene, np.full((6, 46), 1.0), eps)
    assert open_["pb_status"] == "unknown" and open_["pb_rule"] == "linearised"
    # The default limit: 5²³ combinations are not enumerated, and are recorded as a float.
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 10**6)
    offsets = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    _with_regions(monkeypatch, _regions_with(centers, [(k, o) for k in range(23) for o in offsets]))
    huge = _decide(scene, np.zeros((6, 46)), eps)
    assert huge["pb_status"] == "holds" and huge["pb_rule"] == "linearised"
    assert huge["pb_combinations"] == float(5**23) and isinstance(huge["pb_combinations"], float)
    assert huge["pb_exact"] is None


@pytest.mark.parametrize("chunk", [1, 5, 10**5])
def test_enumeration_equals_a_brute_force_loop(scene, monkeypatch, chunk):
    seed, R, t, factors, centers = scene
    rng = np.random.default_rng(chunk)
    moves = [(k, tuple(rng.integers(-3, 4, 2))) for k in (2, 2, 7, 11, 11, 20)]
    pixels = _regions_with(centers, moves)  # 3 · 2 · 3 · 2 = 36 combinations (or fewer)
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


def test_bad_chunks_and_keypoints_are_named(scene):
    seed, R, t, _, _ = scene
    with pytest.raises(ValueError, match="^chunk"):
        rules.enumerated_pose_error(seed, [np.zeros((1, 2))] * 23, R, t, chunk=0)
    with pytest.raises(ValueError, match=r"^keypoints\[1\]"):
        rules.enumerated_pose_error(seed, [np.zeros((1, 2)), np.zeros((0, 2))], R, t)


def _records():
    rows = []
    for image_id, (pb_status, rule, exact) in enumerate(
        [
            ("holds", "enumeration", [1.0] * 6),
            ("unknown", "enumeration", [1.0, 30.0, 1.0, 1.0, 1.0, 1.0]),
            ("violated", "witness", None),
            ("holds", "linearised", None),
            ("unknown", "enumeration", [np.inf] * 6),
        ]
    ):
        rows.append(
            dict(
                kind="brightness",
                level=1.0,
                image_id=image_id,
                alpha=1.0,
                kappa=1.0,
                status="violated",
                time=0.1,
                seed_inside=True,
                counterexample=[0.0],
                pb_status=pb_status,
                pb_rule=rule,
                pb_time=1.0,
                pb_bound=[2.0] * 6,
                pb_exact=exact,
                pb_nonlinear=[1.0] * 6,
            )
        )
    return pd.DataFrame(rows)


def test_tables_count_the_rules_and_label_the_linearised_bound():
    stored = _records()
    from_csv = pd.read_csv(io.StringIO(stored.to_csv(index=False)))
    for records in (stored, from_csv):
        row = tables.t_global(records).iloc[0]
        assert (row.pb_holds, row.pb_violated, row.pb_unknown) == (2, 1, 2)
        assert (row.pb_by_witness, row.pb_by_enumeration, row.pb_by_linearised) == (1, 3, 1)
        assert row.pb_enumeration_holds == 1
        exact = tables.pose_bound_ratios(records, "pb_exact")
        assert exact.image_id.tolist() == [0, 1, 4]
        np.testing.assert_allclose(exact.pitch, [0.1, 3.0, np.inf])
        fig = tables.plot_pose_bounds(records, "T-global")
        ax = fig.axes[0]
        labels = ax.get_legend_handles_labels()[1]
        assert "linearised bound" in labels and "certified" not in ax.get_ylabel()
        assert any(label.startswith("certified") for label in labels)
    # Records from before pb_rule: violated by a witness, the rest by the linearised bound.
    old = stored.drop(columns=["pb_rule", "pb_exact"])
    row = tables.t_global(old).iloc[0]
    assert (row.pb_by_witness, row.pb_by_enumeration, row.pb_by_linearised) == (1, 0, 4)
    assert tables.pose_bound_ratios(old, "pb_exact").empty
    labels = tables.plot_pose_bounds(old, "old").axes[0].get_legend_handles_labels()[1]
    assert "linearised bound" in labels and not any(s.startswith("certified") for s in labels)


def test_the_pose_bound_rate_counts_the_seeds_its_pipeline_gets_right():
    records = _records()  # 5 records, every seed inside Ξ for the target model
    row = tables.t_global(records).iloc[0]
    assert row.pb_seeds_inside == 5 and row.pb_verified_rate == pytest.approx(2 / 5)
    assert row.pb_decided == pytest.approx(3 / 5) and row.decided == 1.0
    # The argmax pipeline right at 3 seeds, both holds among them; the target model at 2.
    records["pb_seed_inside"] = [s == "holds" or i == 2 for i, s in enumerate(records.pb_status)]
    records["seed_inside"] = [True, False, False, True, False]
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        row = tables.t_global(frame).iloc[0]
        assert (row.pb_seeds_inside, row.seeds_inside) == (3, 2)
        assert row.pb_verified_rate == pytest.approx(2 / 3)  # records 0 and 3 of 0, 2, 3
    # A store mixing records with and without the field: the old ones count the target's.
    records["pb_seed_inside"] = records["pb_seed_inside"].astype(object)
    records.loc[[0, 2], "pb_seed_inside"] = None  # target: inside at 0, outside at 2
    row = tables.t_global(records).iloc[0]
    assert row.pb_seeds_inside == 2 and row.pb_verified_rate == 1.0  # records 0 and 3


def test_the_tables_count_the_searches_the_time_cap_ended():
    records = _records()
    records["stopped"] = ["time", "nodes", None, "stop", "time"]
    records["pb_stopped"] = ["nodes", "time", "witness", None, None]
    for frame in (records, pd.read_csv(io.StringIO(records.to_csv(index=False)))):
        row = tables.t_global(frame).iloc[0]
        assert (row.capped, row.pb_capped) == (2, 1)
    from kpstudy.study.report import campaign_summary

    line = campaign_summary(tables.t_global(records))[-1]
    assert "2 of the allocation method's and 1 of the pose-bound method's" in line
    # Records from before the fields: no column, no sentence.
    old = tables.t_global(records.drop(columns=["stopped", "pb_stopped"]))
    assert "capped" not in old and np.isnan(old.pb_capped.iloc[0])
    assert not any("time cap" in s for s in campaign_summary(old))


def test_the_pose_bound_decided_fraction_counts_its_own_records_only():
    records = _records()  # holds, unknown, violated, holds, unknown
    records["pb_status"] = records["pb_status"].astype(object)
    records.loc[4, "pb_status"] = None  # an instance the pose-bound method did not run
    row = tables.t_global(records).iloc[0]
    assert row.pb_decided == pytest.approx(3 / 4) and row.pb_unknown == 1


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
    eps, _ = _far_tolerance(scene)
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
    eps, _ = _far_tolerance(scene)
    centers, pooling, cell, far = _stride1_cells(scene)
    pose = pb.HullPoseBound(_Peaks(centers), _hull(), seed, R, t, np.zeros((6, 46)))
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
    eps, _ = _far_tolerance(scene)
    centers, _, cell, far = _stride1_cells(scene)
    foci = []
    monkeypatch.setattr(pb, "search_regions", _far_pixel_search(scene, foci, nodes=(2, 1)))
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)  # 2 combinations: the linearised rule
    M = np.full((6, 46), 1e3)  # far off: the linearised bound leaves it open
    args = (_Peaks(centers), _hull(), seed, R, t, M, eps)
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
    eps, _ = _far_tolerance(scene)
    centers, *_ = _stride1_cells(scene)
    foci = []
    search = _far_pixel_search(scene, foci, stopped=(first, refinement))
    monkeypatch.setattr(pb, "search_regions", search)
    monkeypatch.setattr(pb, "MAX_COMBINATIONS", 1)  # 2 combinations: the linearised rule
    M = np.full((6, 46), 1e3)  # far off: the linearised bound leaves the tight Ξ open
    loose = np.full(6, 1e9)  # ... and not this one: no focused round
    args = (_Peaks(centers), _hull(), seed, R, t, M)
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
            _Peaks(centers), hull, seed, R, t, M, start_depth=1, start_splits=splits
        )
        assert pose.search["start_depth"] == depth
    for bad in (-0.5, "2", True):
        with pytest.raises(ValueError, match="^start_splits"):
            pb.HullPoseBound(_Peaks(centers), _hull(), seed, R, t, M, start_splits=bad)
