"""kpstudy.certify.allocation_method, kpstudy.certify.hull and kpstudy.study.campaign on a
rendered tiny dataset and a tiny trained CNN."""

import shutil

import numpy as np
import pytest
import torch

from data_gen.perturb import hull_vertices, make_perturbations
from kpstudy.certify.allocation_method import SeedImage, build_instance
from kpstudy.certify.hull import certify
from kpstudy.certify.pose_bound_attack import argmax_outside
from kpstudy.models.data import load_keypoint_set
from kpstudy.models.training import TrainConfig, load_checkpoint, train
from kpstudy.pose.allocation import allocate_tolerances
from kpstudy.pose.geometry import EPS_R, EPS_T
from kpstudy.pose.sensitivity import pose_sensitivity
from kpstudy.study.campaign import (
    Instance,
    ResultStore,
    Settings,
    grid,
    run_campaign,
    run_hull,
    run_study,
    store_path,
)


@pytest.fixture(scope="module")
def study(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset with block and brightness perturbations, and a CNN."""
    data = tmp_path_factory.mktemp("study") / "data"
    shutil.copytree(tiny_dataset, data)
    for kind in ("blocks", "brightness"):
        make_perturbations(data, kind, seeds=2, seed=0, input_size=64)
    checkpoint = data.parent / "cnn.pt"
    train(data, checkpoint, TrainConfig(epochs=2, batch_size=4, images=8, seed=1), progress=False)
    return data, checkpoint


def _seed(data_dir, index=0):
    return SeedImage.from_keypoint_set(load_keypoint_set(data_dir, "test", 64), index)


def test_cells_covering_the_heatmap_hold_and_are_checked_end_to_end(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
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
    seed = _seed(data)
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
    seed = _seed(data)
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


def test_a_study_runs_every_reading_and_the_pose_bound_once(study, tmp_path):
    data, checkpoint = study
    records = run_study(
        {"tiny": str(checkpoint)},
        data,
        ["blocks"],
        tmp_path,
        grid_options=dict(alphas=[0.5], kappas=[1.0], ms=[2], overlapping=[True]),
        tolerance_units=("heatmap", "paper"),
        pose_bound={"tiny": dict(pose_bound_timeout=60.0, pose_bound_nodes=1)},
        timeout=30,
        nodes=2,
        check_samples=0,
    )
    assert len(records) == 2 * 2  # two seed images, two readings
    assert sorted(records.tolerance_units) == ["heatmap", "heatmap", "paper", "paper"]
    assert set(records.model) == {"tiny"} and (records.nodes <= 2).all()
    by = records.set_index("tolerance_units")
    assert by.loc["heatmap", "pb_status"].notna().all()
    assert by.loc["paper", "pb_status"].isna().all()
    assert len(list(tmp_path.glob("blocks-*.sqlite"))) == 2
    with pytest.raises(ValueError, match="^tolerance_units"):
        run_study(
            {"tiny": str(checkpoint)},
            data,
            ["blocks"],
            tmp_path,
            grid_options={},
            tolerance_units=[],
        )


def test_a_model_gets_its_own_allocation_budget(study, tmp_path):
    data, checkpoint = study
    options = dict(
        grid_options=dict(alphas=[0.5], kappas=[1.0], ms=[2], overlapping=[True]),
        timeout=30,
        nodes=2,
        check_samples=0,
    )
    own = dict(method="ibp", nodes=1)
    records = run_study(
        {"tiny": str(checkpoint), "same": str(checkpoint)},
        data,
        ["blocks"],
        tmp_path,
        allocation={"tiny": own},
        **options,
    )
    assert (records[records.model == "tiny"].nodes <= 1).all()
    stores = {p.name for p in tmp_path.glob("blocks-*.sqlite")}
    assert len(stores) == 2  # the settings key the stores: the two budgets, two stores
    alone = run_study({"same": str(checkpoint)}, data, ["blocks"], tmp_path / "alone", **options)
    same = records[records.model == "same"].reset_index(drop=True)
    assert list(same.status) == list(alone.status)
    for bad in ({"vgg": own}, {"tiny": dict(start_splits=2)}):
        with pytest.raises(ValueError, match=r"^allocation: expected \{model of checkpoints"):
            run_study(
                {"tiny": str(checkpoint)}, data, ["blocks"], tmp_path, allocation=bad, **options
            )


def test_certify_bad_input_is_named(study):
    data, checkpoint = study
    backbone, _ = load_checkpoint(checkpoint)
    seed = _seed(data)
    good = hull_vertices(data, seed.image_id, "brightness", level=1.0)
    with pytest.raises(ValueError, match="alpha"):
        certify(backbone, good, seed, alpha=0.0)
    with pytest.raises(ValueError, match="vertices"):
        certify(backbone, good[:1], seed)
    with pytest.raises(ValueError, match="check_samples"):
        certify(backbone, good, seed, check_samples=-1)
    with pytest.raises(ValueError, match="backbone"):
        certify(torch.nn.Identity(), good, seed)


def _instances(data):
    return grid(data, "blocks", alphas=[0.5, 1e4], kappas=[1.0], ms=[2], overlapping=[True])


def test_grid_covers_the_axes_and_refuses_bad_parameters(study):
    data, _ = study
    instances = _instances(data)
    assert len(instances) == 2 * 2  # 2 seed images × 2 α
    assert {(i.alpha, i.m, i.overlapping) for i in instances} == {(0.5, 2, True), (1e4, 2, True)}
    levels = grid(data, "brightness", alphas=[1.0], kappas=[1.0, 1.5])
    assert len(levels) == 2 * 2 * 2 and {i.level for i in levels} == {1.0, 2.0}
    with pytest.raises(ValueError, match="kind"):
        grid(data, "fog", alphas=[1.0], kappas=[1.0])
    with pytest.raises(ValueError, match="alphas"):
        grid(data, "blocks", alphas=[0.0], kappas=[1.0])
    with pytest.raises(ValueError, match="ms: expected hull sizes 1..4"):
        grid(data, "blocks", alphas=[1.0], kappas=[1.0], ms=[5])
    with pytest.raises(ValueError, match="levels"):
        grid(data, "brightness", alphas=[1.0], kappas=[1.0], levels=[3.0])
    with pytest.raises(FileNotFoundError, match="contrast"):
        grid(data, "contrast", alphas=[1.0], kappas=[1.0])


def test_bad_settings_fail_before_any_work(study, tmp_path):
    data, checkpoint = study
    instances = _instances(data)
    bad = [
        (Settings(str(tmp_path / "missing.pt"), str(data)), "checkpoint"),
        (Settings(str(checkpoint), str(tmp_path)), "data_dir"),
        (Settings(str(checkpoint), str(data), method="exact"), "method"),
        (Settings(str(checkpoint), str(data), timeout=0), "timeout"),
        (Settings(str(checkpoint), str(data), nodes=0), "^nodes"),
        (Settings(str(checkpoint), str(data), tolerance_units="px"), "^tolerance_units"),
        (Settings(str(checkpoint), str(data), pose_bound_nodes=-1), "^pose_bound_nodes"),
        (Settings(str(checkpoint), str(data), pose_bound_start_depth=-1), "^pose_bound_start"),
        (Settings(str(checkpoint), str(data), pose_bound_start_depth=99), "^pose_bound_start"),
        (Settings(str(checkpoint), str(data), pose_bound_start_splits=-0.5), "^pose_bound_start_s"),
        (Settings(str(checkpoint), str(data), pose_bound_start_splits=13), "^pose_bound_start_s"),
        (Settings(str(checkpoint), str(data), pose_bound_refine_nodes=-1), "^pose_bound_refine"),
    ]
    for settings, name in bad:
        with pytest.raises((ValueError, FileNotFoundError), match=name):
            run_campaign(instances, tmp_path / "store.sqlite", settings, progress=False)
        assert ResultStore(tmp_path / "store.sqlite").keys() == set()


def _table(frame):
    """The records without their timings, as comparable text."""
    return frame.drop(columns=["time", "total_time"]).to_json(orient="records")


def test_a_killed_campaign_resumes_without_recomputing(study, tmp_path):
    data, checkpoint = study
    instances = _instances(data)
    settings = Settings(str(checkpoint), str(data), timeout=600, nodes=50, check_samples=4)
    straight = run_campaign(instances, tmp_path / "straight.sqlite", settings, progress=False)
    assert len(straight) == len(instances)

    class Killed(Exception):
        pass

    def kill_after_two(instance, record, seen=[]):  # noqa: B006
        seen.append(instance)
        if len(seen) == 2:
            raise Killed

    store = tmp_path / "killed.sqlite"
    with pytest.raises(Killed):
        run_campaign(instances, store, settings, progress=False, on_record=kill_after_two)
    assert len(ResultStore(store).keys()) == 2
    computed = []
    resumed = run_campaign(
        instances, store, settings, progress=False, on_record=lambda i, r: computed.append(i)
    )
    assert len(computed) == len(instances) - 2
    assert _table(resumed) == _table(straight)
    again = []
    run_campaign(instances, store, settings, progress=False, on_record=lambda i, r: again.append(i))
    assert again == []


@pytest.mark.slow
def test_dask_and_process_pool_runs_equal_the_local_run(study, tmp_path):
    from distributed import LocalCluster

    data, checkpoint = study
    instances = _instances(data)[:2]
    settings = Settings(str(checkpoint), str(data), timeout=600, nodes=50, check_samples=4)
    local = _table(run_campaign(instances, tmp_path / "local.sqlite", settings, progress=False))
    pool = run_campaign(instances, tmp_path / "pool.sqlite", settings, workers=2, progress=False)
    assert _table(pool) == local
    with LocalCluster(
        n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None
    ) as c:
        dask = run_campaign(
            instances,
            tmp_path / "dask.sqlite",
            settings,
            scheduler=c.scheduler_address,
            progress=False,
        )
    assert _table(dask) == local


def test_run_hull_gives_each_cell_its_record_and_the_clipped_fraction(study):
    data, checkpoint = study
    seed = _seed(data)
    settings = Settings(str(checkpoint), str(data), timeout=600, nodes=2, check_samples=0)
    cells = [Instance("brightness", seed.image_id, a, k, level=2.0) for a, k in [(1, 1), (5, 2)]]
    both = run_hull(cells, settings)
    assert 0.0 <= both[0]["clipped_fraction"] < 1.0
    for instance, record in zip(cells, both):  # the same as each cell alone
        (alone,) = run_hull([instance], settings)
        for key in ("status", "dv", "nodes", "seed_error", "clipped_fraction"):
            assert record[key] == alone[key]
    assert both[0]["dv"] != both[1]["dv"]
    blocks = Instance("blocks", seed.image_id, 1.0, 1.0, m=1, overlapping=False)
    assert run_hull([blocks], settings)[0]["clipped_fraction"] == 0.0
    with pytest.raises(ValueError, match="^instances: expected the instances of one hull"):
        run_hull([cells[0], blocks], settings)


def test_store_paths_separate_models_and_settings(study, tmp_path, monkeypatch):
    data, checkpoint = study
    settings = Settings(str(checkpoint), str(data), timeout=5)
    path = store_path(tmp_path, "objects", settings)
    assert path == store_path(tmp_path, "objects", Settings(str(checkpoint), str(data), timeout=5))
    assert path.parent == tmp_path and path.name.startswith("objects-")
    assert path != store_path(tmp_path, "objects", Settings(str(checkpoint), str(data), timeout=6))
    other = tmp_path / "other.pt"
    state = torch.load(checkpoint, weights_only=True)
    state["epoch"] += 1
    torch.save(state, other)
    assert path != store_path(tmp_path, "objects", Settings(str(other), str(data), timeout=5))
    monkeypatch.setattr("kpstudy.study.campaign.source_fingerprint", lambda: "other code")
    assert path != store_path(tmp_path, "objects", settings)


def test_the_command_line_offers_every_setting_with_its_default():
    import argparse
    from dataclasses import fields

    from kpstudy.study.campaign import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    defaults = parser.parse_args([])
    args = argparse.Namespace(checkpoint="c.pt", data="d", **vars(defaults))
    assert Settings.from_arguments(args) == Settings("c.pt", "d")
    chosen = parser.parse_args(["--pose-bound-nodes", "3", "--timeout", "2.5", "--method", "ibp"])
    settings = Settings.from_arguments(argparse.Namespace(checkpoint="c", data="d", **vars(chosen)))
    assert (settings.pose_bound_nodes, settings.timeout, settings.method) == (3, 2.5, "ibp")
    offered = {a.dest for a in parser._actions} - {"help"}
    assert offered == {f.name for f in fields(Settings)} - {"checkpoint", "data_dir"}
    options = settings.certify_options()
    assert options["max_nodes"] == settings.nodes and "nodes" not in options
    assert options["pose_bound_nodes"] == 3 and "checkpoint" not in options
