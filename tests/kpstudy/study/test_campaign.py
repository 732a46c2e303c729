"""kpstudy.study.campaign on a rendered tiny dataset and a tiny trained CNN: grids,
settings, studies, resuming, pools; and campaigns a careless or hostile user cannot break
(issue 29, points 1–3 and the campaign's cases of point 7): a store refuses another
campaign's settings, workers die with their parent, a seed that cannot be certified is an
``error`` record, and bad ``--store`` / ``--timeout`` / ``--scheduler`` arguments exit 2
with one line and nothing written."""

import io
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch

from data_gen.perturb import make_perturbations
from kpstudy.cli import main
from kpstudy.models.training import TrainConfig, train
from kpstudy.study import campaign, tables
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
from tests.conftest import seed_image


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
    return frame.drop(columns=["time", "total_time", "peak_memory_mib"]).to_json(orient="records")


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


def test_run_hull_gives_each_cell_its_record_the_clipped_fraction_and_peak_memory(study):
    data, checkpoint = study
    seed = seed_image(data)
    settings = Settings(str(checkpoint), str(data), timeout=600, nodes=2, check_samples=0)
    cells = [Instance("brightness", seed.image_id, a, k, level=2.0) for a, k in [(1, 1), (5, 2)]]
    both = run_hull(cells, settings)
    assert 0.0 <= both[0]["clipped_fraction"] < 1.0
    assert both[0]["peak_memory_mib"] == both[1]["peak_memory_mib"] > 10  # this process's
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


ROOT = Path(__file__).resolve().parents[3]

BAD_IMAGE = 18  # the tiny dataset's second test image


@pytest.fixture(scope="module")
def two_checkpoints(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset with block perturbations, a CNN and a second checkpoint
    (the same weights, another epoch count: other bytes)."""
    data = tmp_path_factory.mktemp("reliability") / "data"
    shutil.copytree(tiny_dataset, data)
    make_perturbations(data, "blocks", seeds=2, seed=0, input_size=64)
    checkpoint = data.parent / "cnn.pt"
    train(data, checkpoint, TrainConfig(epochs=2, batch_size=4, images=8, seed=1), progress=False)
    other = data.parent / "other.pt"
    state = torch.load(checkpoint, weights_only=True)
    state["epoch"] += 1
    torch.save(state, other)
    return data, checkpoint, other


def _small_grid(data):
    return grid(data, "blocks", alphas=[0.5, 1e4], kappas=[1.0], ms=[1], overlapping=[False])


def _settings(checkpoint, data, **kw):
    return Settings(str(checkpoint), str(data), **{"timeout": 10, "check_samples": 0, **kw})


def _cli(capsys, *argv):
    """``python -m kpstudy campaign ARGV`` in this process: (exit status, stderr)."""
    try:
        status = main(["campaign", *map(str, argv)])
    except SystemExit as exc:
        status = exc.code
    return status, capsys.readouterr().err


def _one_line(err, *words):
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for word in words:
        assert word in lines[0], lines[0]


def test_a_store_made_by_another_checkpoint_or_settings_is_refused(
    two_checkpoints, tmp_path, capsys
):
    data, checkpoint, other = two_checkpoints
    instances = _small_grid(data)[:1]
    store = tmp_path / "s.sqlite"
    first = run_campaign(instances, store, _settings(checkpoint, data), progress=False)
    assert len(first) == 1
    before = store.read_bytes()

    with pytest.raises(ValueError, match=r"store: .*another campaign \(its checkpoint differ"):
        run_campaign(instances, store, _settings(other, data), progress=False)
    with pytest.raises(ValueError, match=r"store: .*its timeout 10.0 \(here 11.0\) differ"):
        run_campaign(instances, store, _settings(checkpoint, data, timeout=11), progress=False)
    # The case: the same command with another checkpoint, method and timeout.
    out = tmp_path / "out"
    status, err = _cli(
        capsys,
        *("--checkpoint", other, "--data", data, "--kind", "blocks", "--alphas", 0.5),
        *("--ms", 1, "--seeds", 1, "--method", "ibp", "--timeout", 999),
        *("--store", store, "--out", out),
    )
    assert status == 2
    _one_line(err, "store:", "checkpoint", "method 'auto' (here 'ibp')")
    assert store.read_bytes() == before and not list(tmp_path.glob("out*"))
    # The same campaign still resumes from it, computing nothing.
    again = []
    resumed = run_campaign(
        instances,
        store,
        _settings(checkpoint, data),
        progress=False,
        on_record=lambda i, r: again.append(i),
    )
    assert again == [] and resumed.to_json() == first.to_json()


def test_a_store_of_unknown_provenance_with_records_is_refused(two_checkpoints, tmp_path):
    data, checkpoint, _ = two_checkpoints
    legacy = tmp_path / "legacy.sqlite"
    with sqlite3.connect(legacy) as db:  # a store as written before stores kept provenance
        db.execute("CREATE TABLE records (key TEXT PRIMARY KEY, record TEXT)")
        db.execute("INSERT INTO records VALUES ('k', '{\"status\": \"holds\"}')")
    with pytest.raises(ValueError, match="store: .*unknown provenance"):
        run_campaign(_small_grid(data), legacy, _settings(checkpoint, data), progress=False)
    assert ResultStore(legacy).keys() == {"k"}  # still readable


def _state(pid):
    """The process state letter of ``pid`` (``None``: gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2]


def _children(pid):
    """Live child processes of ``pid``: {pid: command line}."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            out[int(entry.name)] = command
    return out


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc (Linux)")
@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_killing_a_campaign_leaves_no_worker_behind(two_checkpoints, tmp_path, signum):
    data, checkpoint, _ = two_checkpoints
    command = [
        *(sys.executable, "-m", "kpstudy", "campaign", "--checkpoint", checkpoint),
        *("--data", data, "--kind", "blocks", "--alphas", 0.5, 0.7, 1.0, 2.0, 3.0),
        *("--ms", 1, 2, 3, "--workers", 2, "--store", tmp_path / "s.sqlite"),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    parent = subprocess.Popen(
        [str(c) for c in command],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    children = {}
    try:
        deadline = time.monotonic() + 120  # two workers importing torch on a busy machine
        while time.monotonic() < deadline and parent.poll() is None:
            children = _children(parent.pid)
            if sum("spawn_main" in c for c in children.values()) == 2:
                break
            time.sleep(0.1)
        assert sum("spawn_main" in c for c in children.values()) == 2, (
            f"no two workers: {children}; stderr: {parent.stderr.read().decode()[-2000:]}"
            if parent.poll() is not None
            else f"no two workers: {children}"
        )
        parent.send_signal(signum)
        parent.wait(30)
        deadline = time.monotonic() + 120  # only a worker that never exits reaches it
        while time.monotonic() < deadline and any(_state(p) not in (None, "Z") for p in children):
            time.sleep(0.1)
        left = {p: c for p, c in children.items() if _state(p) not in (None, "Z")}
        assert not left, f"alive after the parent's {signum.name}: {left}"
        assert "Traceback" not in parent.stderr.read().decode()
    finally:
        for pid in [parent.pid, *children]:
            if _state(pid) not in (None, "Z"):
                os.kill(pid, signal.SIGKILL)
        parent.wait(30)
        parent.stderr.close()


@pytest.fixture(scope="module")
def bad_seed(two_checkpoints):
    """The study's dataset with keypoint 0 of one seed image outside the image."""
    data, checkpoint, _ = two_checkpoints
    bad = data.parent / "bad"
    shutil.copytree(data, bad)
    path = bad / "annotations.json"
    coco = json.loads(path.read_text())
    annotation = next(a for a in coco["annotations"] if a["image_id"] == BAD_IMAGE)
    annotation["keypoints"][0:2] = [-40.0, -40.0]
    path.write_text(json.dumps(coco))
    return bad, checkpoint


def test_a_seed_that_cannot_be_certified_is_stored_as_an_error(bad_seed, tmp_path):
    data, checkpoint = bad_seed
    instances = _small_grid(data)
    assert len(instances) == 4 and {i.image_id for i in instances} == {9, BAD_IMAGE}
    settings = _settings(checkpoint, data)
    store = tmp_path / "s.sqlite"
    frame = run_campaign(instances, store, settings, progress=False)

    assert len(frame) == len(instances) == len(ResultStore(store).keys())
    bad = frame[frame.image_id == BAD_IMAGE]
    good = frame[frame.image_id != BAD_IMAGE]
    assert list(bad.status) == ["error", "error"]
    assert all(isinstance(e, str) and "ValueError" in e for e in bad.error)
    assert set(good.status) <= {"holds", "violated", "unknown"}
    assert good.error.isna().all()

    # A rerun completes without recomputing anything; retry_errors reruns the errors only.
    again = []
    rerun = run_campaign(
        instances, store, settings, progress=False, on_record=lambda i, r: again.append(i)
    )
    assert again == [] and list(rerun.status) == list(frame.status)
    retried = []
    run_campaign(
        instances,
        store,
        settings,
        progress=False,
        retry_errors=True,
        on_record=lambda i, r: retried.append(i),
    )
    assert {i.image_id for i in retried} == {BAD_IMAGE} and len(retried) == 2

    # The tables count errors apart: never decided, never verified, not in the rates.
    from_csv = pd.read_csv(io.StringIO(frame.to_csv(index=False)))
    for records in (frame, from_csv):
        table = tables.summarise(records, ["alpha"])
        assert list(table.instances) == [2, 2] and list(table.errors) == [1, 1]
        decided = table.holds + table.violated + table.unknown
        assert list(decided) == [1, 1]
        good_inside = good.groupby("alpha")["seed_inside"].sum().to_numpy()
        assert list(table.seeds_inside) == list(good_inside)
    only_errors = tables.summarise(frame[frame.status == "error"][["alpha", "status"]], ["alpha"])
    assert list(only_errors.errors) == [1, 1] and list(only_errors.holds) == [0, 0]


def _base(two_checkpoints):
    data, checkpoint, _ = two_checkpoints
    return (
        *("--checkpoint", checkpoint, "--data", data, "--kind", "blocks"),
        *("--alphas", 1e4, "--ms", 1, "--seeds", 1, "--timeout", 5),
    )


NOTES = "these are my notes, not a database\n" * 10


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (("--store", "{tmp}/a_file/sub/s.sqlite"), ("store:", "not a directory")),
        (("--store", "{tmp}/notes.sqlite"), ("store:", "SQLite")),
        (("--timeout", 0, "--store", "{tmp}/fresh/s.sqlite"), ("timeout:",)),
        (("--nodes", 0, "--store", "{tmp}/fresh/s.sqlite"), ("nodes:",)),
        (("--pose-bound-stride", 2, "--store", "{tmp}/fresh/s.sqlite"), ("pose_bound_stride:",)),
        (("--check-samples", -1, "--store", "{tmp}/fresh/s.sqlite"), ("check_samples:",)),
        (
            ("--tolerance-units", "pixels", "--store", "{tmp}/fresh/s.sqlite"),
            ("tolerance_units:", "pixels"),
        ),
        (
            ("--scheduler", "tcp://127.0.0.1:1", "--store", "{tmp}/fresh/s.sqlite"),
            ("scheduler:", "tcp://127.0.0.1:1"),
        ),
    ],
    ids=[
        "store_uncreatable",
        "store_not_sqlite",
        "timeout_0",
        "nodes_0",
        "stride_even",
        "check_samples_negative",
        "tolerance_units_unknown",
        "scheduler_unreachable",
    ],
)
def test_campaign_argument_errors_are_one_line_and_write_nothing(
    two_checkpoints, tmp_path, capsys, argv, words
):
    (tmp_path / "a_file").write_text("not a folder")
    (tmp_path / "notes.sqlite").write_text(NOTES)
    argv = [str(a).format(tmp=tmp_path) for a in argv]
    status, err = _cli(capsys, *_base(two_checkpoints), *argv)
    assert status == 2
    _one_line(err, *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "notes.sqlite"]
    assert (tmp_path / "a_file").read_text() == "not a folder"
    assert (tmp_path / "notes.sqlite").read_text() == NOTES


def _broken(two_checkpoints, tmp_path, what):
    """The study's checkpoint and dataset with one input made unusable: (checkpoint, data,
    the unusable file)."""
    data, checkpoint, _ = two_checkpoints
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    if what == "checkpoint":
        bad = inputs / "truncated.pt"
        whole = checkpoint.read_bytes()
        bad.write_bytes(whole[: len(whole) // 2])
        return bad, data, bad
    copy = inputs / "data"
    shutil.copytree(data, copy)
    if what == "annotations":
        bad = copy / "annotations.json"
        text = bad.read_text()
        bad.write_text(text[: len(text) // 2])
    else:  # the blocks set's seed image of the first seed, which each of its hulls needs
        meta = json.loads((copy / "perturbations" / "blocks" / "meta.json").read_text())
        bad = copy / "perturbations" / "blocks" / meta["images"][0]["seed_file"]
        bad.unlink()
    return checkpoint, copy, bad


@pytest.mark.parametrize(
    ("what", "name"),
    [("checkpoint", "checkpoint:"), ("annotations", "data_dir:"), ("perturbed", "data_dir:")],
)
def test_an_unusable_input_is_refused_before_the_store_is_made(
    two_checkpoints, tmp_path, capsys, what, name
):
    checkpoint, data, bad = _broken(two_checkpoints, tmp_path, what)
    run = tmp_path / "run"
    status, err = _cli(
        capsys,
        *("--checkpoint", checkpoint, "--data", data, "--kind", "blocks", "--alphas", 1e4),
        *("--ms", 1, "--seeds", 1, "--timeout", 5, "--nodes", 2),
        *("--store", run / "s.sqlite", "--out", run / "records"),
    )
    assert status == 2
    _one_line(err, name, str(bad))
    assert not run.exists()
    settings = _settings(checkpoint, data)
    with pytest.raises(ValueError, match=f"^{name}"):
        run_campaign(_small_grid(data), run / "s.sqlite", settings, progress=False)
    assert not run.exists()


def test_a_campaign_with_error_instances_exits_non_zero_and_lists_them(bad_seed, tmp_path, capsys):
    data, checkpoint = bad_seed
    argv = (
        *("--checkpoint", checkpoint, "--data", data, "--kind", "blocks", "--alphas", 0.5, 1e4),
        *("--ms", 1, "--timeout", 10, "--nodes", 2, "--check-samples", 0),
        *("--store", tmp_path / "s.sqlite"),
    )
    for _ in ("run", "resume"):  # a resumed campaign reports the stored errors too
        status, err = _cli(capsys, *argv)
        assert status == 1, err
        assert "Traceback" not in err
        lines = err.strip().splitlines()
        listed = [line for line in lines[:-1] if f'"image_id": {BAD_IMAGE}' in line]
        assert len(listed) == 4 and all("ValueError" in line for line in listed), err
        assert "4 of 8 instances ended 'error'" in lines[-1] and "--retry-errors" in lines[-1]
    assert len(ResultStore(tmp_path / "s.sqlite").keys(errors=False)) == 4


def test_reproduce_exits_non_zero_when_a_campaign_instance_ended_error(tmp_path, capsys):
    tables = tmp_path / "results" / "quick" / "tables"
    tables.mkdir(parents=True)
    records = pd.DataFrame(
        {
            "kind": ["objects", "objects"],
            "image_id": [9, BAD_IMAGE],
            "alpha": [1.0, 1.0],
            "kappa": [1.0, 1.0],
            "m": [2, 2],
            "overlapping": [False, False],
            "model": ["cnn", "cnn"],
            "tolerance_units": ["heatmap", "heatmap"],
            "status": ["holds", "error"],
            "error": [None, "ValueError: keypoint 0 outside the image"],
        }
    )
    records.to_csv(tables / "t_local_records.csv", index=False)
    try:
        status = main(["reproduce", "--out", str(tmp_path / "results"), "--stages", "report"])
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    assert status == 1, captured.err
    assert "Traceback" not in captured.err
    assert f"image {BAD_IMAGE}" in captured.out and "keypoint 0 outside" in captured.out
    last = captured.err.strip().splitlines()[-1]
    assert "1 of 2 campaign instances ended 'error'" in last and "t_local_records.csv" in last
    assert (tmp_path / "results" / "quick" / "REPORT.md").is_file()  # the report is written


HOLDER = """
import sys, threading
from pathlib import Path
from kpstudy.study import campaign
from kpstudy.study.campaign import Settings, grid, run_campaign

data, checkpoint, store, marker, code = sys.argv[1:]
# The test's code fingerprint: an edit to the tree while the tests run changes nothing here.
campaign.source_fingerprint = lambda: code
instances = grid(data, "blocks", alphas=[0.5, 1e4], kappas=[1.0], ms=[1], overlapping=[False])
settings = Settings(checkpoint, data, timeout=600, check_samples=0, nodes=2)
seen = []

def hold(instance, record):
    seen.append(instance)
    if len(seen) == 2:  # the first hull is stored: hold the store until killed
        Path(marker).write_text("holding")
        threading.Event().wait()

run_campaign(instances, store, settings, progress=False, on_record=hold)
"""


def _records(frame):
    """The records without their timings, as comparable text."""
    return frame.drop(columns=["time", "total_time", "peak_memory_mib"]).to_json(orient="records")


def test_one_store_takes_one_live_campaign_and_a_killed_one_resumes_exactly(
    two_checkpoints, tmp_path, capsys
):
    data, checkpoint, _ = two_checkpoints
    instances = _small_grid(data)  # two hulls of two cells each
    # A node budget decides; the 600 s cap only stops a hang (a fired cap would differ).
    settings = _settings(checkpoint, data, nodes=2, timeout=600)
    straight = run_campaign(instances, tmp_path / "straight.sqlite", settings, progress=False)
    assert len(straight) == 4
    store, marker, log = tmp_path / "s.sqlite", tmp_path / "holding", tmp_path / "holder.err"
    code = campaign.source_fingerprint()
    with open(log, "wb") as err:
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLDER, *map(str, (data, checkpoint, store, marker, code))],
            cwd=ROOT,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    try:
        deadline = time.monotonic() + 300  # importing torch on a busy machine
        while not marker.exists() and holder.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert marker.exists(), log.read_text()[-2000:]
        assert len(ResultStore(store).keys()) == 2

        # A second campaign on the store, in this process and from the command line.
        with pytest.raises(ValueError, match=r"^store: .* is in use by a running campaign"):
            run_campaign(instances, store, settings, progress=False)
        status, err = _cli(
            capsys,
            *("--checkpoint", checkpoint, "--data", data, "--kind", "blocks"),
            *("--alphas", 0.5, 1e4, "--ms", 1, "--timeout", 600, "--check-samples", 0),
            *("--nodes", 2, "--store", store),
        )
        assert status == 2
        _one_line(err, "store:", str(store), "in use")
        assert len(ResultStore(store).keys()) == 2
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(30)

    # The killed campaign's store resumes: the rest is computed, the records are the
    # uninterrupted run's.
    computed = []
    resumed = run_campaign(
        instances, store, settings, progress=False, on_record=lambda i, r: computed.append(i)
    )
    assert len(computed) == 2
    assert _records(resumed) == _records(straight)
    assert sorted(p.name for p in tmp_path.glob("s.sqlite*")) == ["s.sqlite"]
