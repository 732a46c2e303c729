"""kpstudy.study.reproduction: `python -m kpstudy reproduce` end to end at a tiny scale (data
→ train → the eight notebooks under papermill → REPORT.md; a rerun finds everything
current), the shipped ResNet-18 checkpoint (written, copied or retrained), and the
notebooks' kernels: over IPC (no IPKernel eavesdropping warning), their own diagnostics
in a log file."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest

from kpstudy.study.report import SECTIONS
from kpstudy.study.reproduction import (
    NOTEBOOKS,
    PROFILES,
    SHIPPED,
    compare_results,
    profile,
    reproduce,
)
from kpstudy.study.tables import PAPER_T_PROB

# A tiny variant of the standard profile: its readings, the zonotope under node budgets,
# object sets with patches aimed at the airplane.
TINY = replace(
    PROFILES["standard"],
    name="tiny",
    dataset_images=20,
    dataset_size="160x100",
    perturbed_seeds=2,
    cnn_epochs=1,
    cnn_images=8,
    resnet_epochs=1,
    resnet_images=4,
    images=2,
    samples=20,
    seeds=1,
    resnet_seeds=1,
    timeout=60.0,
    resnet_timeout=60.0,
    nodes=2,
    local_pose_bound={
        "cnn": dict(pose_bound_timeout=60.0, pose_bound_nodes=1),
        "cnn_patch_smooth": dict(
            pose_bound_method="zonotope",
            pose_bound_timeout=60.0,
            pose_bound_nodes=2,
            pose_bound_start_depth=1,
        ),
    },
    global_pose_bound={
        m: dict(pose_bound_timeout=60.0, pose_bound_nodes=1) for m in ("cnn", "cnn_patch_smooth")
    },
    figure_images=2,
    workers=1,
)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    return reproduce(TINY, root, progress=False)


@pytest.mark.slow
def test_every_table_and_figure_is_written_and_reported(run):
    report = (run / "REPORT.md").read_text()
    assert "missing" not in report
    for title, notebook, tables, figures, _ in SECTIONS:
        assert f"## {title}" in report
        assert (run / "notebooks" / f"{notebook}.ipynb").is_file()
        for name in tables:
            assert (run / "tables" / f"{name}.csv").is_file()
            assert (run / "tables" / f"{name}.md").read_text() in report
        for name in figures:
            assert (run / "figures" / f"{name}.png").stat().st_size > 1000
    assert not list(run.rglob(".*.tmp"))  # no leftovers of the atomic writes


@pytest.mark.slow
def test_tables_hold_the_grid_and_the_papers_numbers(run):
    prob = pd.read_csv(run / "tables" / "t_prob.csv")
    assert set(zip(prob.kappa, prob.alpha)) == set(PAPER_T_PROB)
    assert prob.soundness.between(0, 1).all() and (prob.samples == 40).all()
    assert sorted(set(prob.tolerance_units)) == ["heatmap", "paper"] and len(prob) == 24
    local = pd.read_csv(run / "tables" / "t_local.csv")
    assert set(local.kappa) == {1.0, 1.5} and set(local.alpha) == {1.0, 1.5}
    assert local.paper_rate.notna().all()
    records = pd.read_csv(run / "tables" / "t_local_records.csv")
    assert local.instances.sum() == len(records) > 0
    counts = local.holds + local.violated + local.unknown + local.not_certifiable
    assert (counts == local.instances).all()
    # Half of each seed's object patches aimed at the airplane: overlapping hulls exist.
    assert local[local.overlapping.astype(bool)].instances.sum() > 0
    # The sound reading's cells keep the first-order bound from the exact keypoint.
    sound = records[(records.tolerance_units == "heatmap") & (records.status != "not_certifiable")]
    assert len(sound) and (sound.first_order <= 1 + 1e-9).all()
    # The pose-bound method on the same instances, and what each method alone verifies.
    heat = local[local.tolerance_units == "heatmap"]  # the pose-bound method runs once
    assert (heat.pb_holds <= heat.instances).all() and heat.pb_time_mean.gt(0).all()
    assert local[local.tolerance_units == "paper"].pb_holds.isna().all()
    assert {"pb_only", "allocation_only", "pb_verified_rate"} <= set(local.columns)
    # Both readings of the tolerances; the pose-bound method (no tolerances) runs once.
    assert set(local.tolerance_units) == {"heatmap", "paper"}
    heatmap = records[records.tolerance_units == "heatmap"]
    assert heatmap.pb_status.isin(["holds", "violated", "unknown"]).all()
    assert records[records.tolerance_units == "paper"].pb_status.isna().all()
    assert "reading" in (run / "REPORT.md").read_text()
    assert "Pose-bound method" in (run / "REPORT.md").read_text()
    glob = pd.read_csv(run / "tables" / "t_global.csv")
    # Both CNNs, row by row: the paper's and the verification-friendly one.
    assert set(local.model) == set(glob.model) == {"cnn", "cnn_patch_smooth"}
    assert set(records.model) == {"cnn", "cnn_patch_smooth"}
    assert set(glob.kind) == {"brightness", "contrast"} and len(glob) == 2 * 2 * 5 * 4
    assert "`cnn_patch_smooth`: " in (run / "REPORT.md").read_text()
    assert glob.paper_time_mean.notna().all() and (glob.clipped_fraction >= 0).all()
    resnet = pd.read_csv(run / "tables" / "t_resnet.csv")
    assert set(resnet.overlapping) == {False, True} and (resnet.alpha == 1.5).all()


@pytest.mark.slow
def test_a_second_run_gives_the_same_tables_and_models(run, tmp_path_factory):
    """Two runs of a profile from scratch: every table cell (timing columns aside) and
    every checkpoint's weights agree (before the tests below change ``run``)."""
    again = reproduce(TINY, tmp_path_factory.mktemp("again"), progress=False)
    found = compare_results(run, again)
    assert {"tables/t_local_records.csv", "tables/t_global.csv", "models/cnn.pt"} <= set(found)
    assert set(found.values()) == {"same"}, found


@pytest.mark.slow
def test_a_rerun_finds_every_stage_current(run, capsys):
    stamps = {p.name: p.read_text() for p in (run / "notebooks").glob("*.json")}
    reproduce(TINY, run.parent, progress=False)
    out = capsys.readouterr().out
    assert out.count("current, skipped") == 8
    assert {p.name: p.read_text() for p in (run / "notebooks").glob("*.json")} == stamps


@pytest.mark.slow
def test_a_changed_parameter_reruns_only_its_notebooks(run, capsys):
    reproduce(replace(TINY, samples=10), run.parent, stages=("notebooks",), progress=False)
    out = capsys.readouterr().out
    assert "05_probabilistic: running" in out and out.count("current, skipped") == 7
    assert (
        json.loads((run / "notebooks" / "05_probabilistic.json").read_text())["parameters"][
            "samples"
        ]
        == 10
    )


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(seeds=9), "seeds: expected at most perturbed_seeds=8"),
        (dict(timeout=0), "timeout: expected a positive number"),
        (dict(overlapping_share=1.5), "overlapping_share: expected None or [0, 1], got 1.5"),
        (dict(speed=2), "overrides: unknown profile fields ['speed']"),
        (dict(nodes=0), "nodes: expected a positive number"),
        (dict(tolerance_units=("pixels",)), "tolerance_units: expected a tuple of distinct"),
        (dict(tolerance_units=()), "tolerance_units: expected a tuple of distinct"),
        (
            dict(global_pose_bound={"cnn": {"pose_bound_method": "crown"}}),
            "global_pose_bound: pose_bound_method: expected one of ibp, forward, zonotope, "
            "got 'crown'",
        ),
        (
            dict(local_pose_bound={"cnn": {"pose_bound_speed": 2}}),
            "local_pose_bound: unknown settings ['pose_bound_speed']",
        ),
        (
            dict(local_pose_bound={"vgg": {}}),
            "local_pose_bound: expected {'cnn' or 'cnn_patch_smooth'",
        ),
        (
            dict(resnet_pose_bound={"cnn": {}}),
            "resnet_pose_bound: expected {'resnet18': {setting: value}}, got 'cnn': {}",
        ),
        (
            dict(resnet_pose_bound={"resnet18": {"pose_bound_nodes": -1}}),
            "resnet_pose_bound: pose_bound_nodes: expected None or an integer >= 0, got -1",
        ),
        (
            dict(allocation={"vgg": {"nodes": 2}}),
            "allocation: expected {'cnn' or 'cnn_patch_smooth': {setting: value}}",
        ),
        (dict(allocation={"cnn": {"nodes": 0}}), "allocation: nodes: expected None or a positive"),
        (dict(allocation={"cnn": {"timeout": 0}}), "allocation: timeout: expected seconds > 0"),
        (
            dict(local_pose_bound={"cnn": {"pose_bound_nodes": -1}}),
            "local_pose_bound: pose_bound_nodes: expected None or an integer >= 0, got -1",
        ),
        (
            dict(global_pose_bound={"cnn": {"pose_bound_timeout": 0}}),
            "global_pose_bound: pose_bound_timeout: expected None or seconds > 0, got 0",
        ),
        (
            dict(allocation={"cnn": {"method": "crown2"}}),
            "allocation: method: expected 'auto' or one of",
        ),
    ],
)
def test_bad_profiles_are_refused_before_any_work(overrides, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        profile("quick", **overrides)


def test_a_code_change_makes_every_notebook_stale(monkeypatch):
    from kpstudy.study import reproduction as module

    source = NOTEBOOKS / "05_probabilistic.ipynb"
    before = module._signature(source, {"images": 2})
    assert before == module._signature(source, {"images": 2})
    monkeypatch.setattr(module, "source_fingerprint", lambda: "other code")
    assert module._signature(source, {"images": 2}) != before


@pytest.mark.parametrize("name", [s[1] for s in SECTIONS])
def test_notebooks_in_git_are_stripped_and_parameterised(name):
    import nbformat

    book = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbformat.validate(book)
    code = [c for c in book.cells if c.cell_type == "code"]
    assert all(not c.outputs and c.execution_count is None for c in code)
    tagged = [c for c in code if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and tagged[0] is code[0]
    assert "out = " in tagged[0].source


def _results(root, **tables):
    (root / "tables").mkdir(parents=True)
    for name, text in tables.items():
        (root / "tables" / f"{name}.csv").write_text(text)
    return root


def test_compare_results_names_what_differs_and_sets_timing_and_memory_aside(tmp_path):
    a = _results(
        tmp_path / "a",
        t="status,pb_time,capped,peak_memory_mib\nholds,1.0,0,900\nunknown,2.0,0,900\n",
        only_a="x\n1\n",
        rows="x\n1\n",
    )
    b = _results(
        tmp_path / "b",
        t="status,pb_time,capped,peak_memory_mib\nholds,7.5,0,1100\nholds,300.0,1,1100\n",
        rows="x\n1\n2\n",
    )
    assert compare_results(a, b) == {
        "tables/only_a.csv": "only in a",
        "tables/rows.csv": "shape differs: (1, 1) against (2, 1)",
        "tables/t.csv": "cells differ: status (1), capped (1)",
    }
    with pytest.raises(ValueError, match=r"^b: expected a results folder with tables/"):
        compare_results(a, tmp_path / "missing")


def test_compare_cli_exits_1_on_a_difference_and_2_on_bad_input(tmp_path, capsys):
    from kpstudy.cli import main

    a = _results(tmp_path / "a", t="status,time\nholds,1\n")
    b = _results(tmp_path / "b", t="status,time\nholds,2\n")
    c = _results(tmp_path / "c", t="status,time\nviolated,1\n")
    assert main(["compare", str(a), str(b)]) == 0
    assert main(["compare", str(a), str(c)]) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "tables/t.csv: cells differ: status (1)"
    with pytest.raises(SystemExit) as exit_:
        main(["compare", str(a), str(tmp_path / "none")])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().startswith("kpstudy compare: error: b: expected")


def test_the_standard_profile_reaches_the_campaigns_and_notebooks_run_alone(tmp_path, monkeypatch):
    """Its counts and every method's budgets are what notebooks 06–08 get; ``only`` runs the
    named notebooks and no other."""
    import papermill

    from kpstudy.study import reproduction as module

    ran = {}

    def execute(source, target, parameters, **_):
        ran[Path(source).stem] = parameters

    monkeypatch.setattr(papermill, "execute_notebook", execute)
    prof = profile("standard")
    assert prof.seeds >= 50 and prof.resnet_seeds >= 50 and prof.method == "auto"
    module.run_notebooks(prof, tmp_path, progress=False, only=["06_local", "07_global"])
    assert sorted(ran) == ["06_local", "07_global"]
    local, global_ = ran["06_local"], ran["07_global"]
    assert local["seeds"] == 50 and local["method"] == "auto" and local["nodes"] == prof.nodes
    for model in ("cnn", "cnn_patch_smooth"):  # every model's pose-bound method: the zonotope
        assert local["pose_bound"][model]["pose_bound_method"] == "zonotope"
        assert local["pose_bound"][model]["pose_bound_nodes"] >= 1
        assert global_["pose_bound"][model]["pose_bound_method"] == "zonotope"
    assert local["tolerance_units"] == ["heatmap", "paper"]
    assert local["allocation"] == global_["allocation"] == prof.allocation
    with pytest.raises(ValueError, match=r"^notebooks: expected some of \["):
        reproduce(prof, tmp_path, stages=("notebooks",), notebooks=["09_nothing"])


def test_ship_half_writes_float16_weights_that_load_as_float32_and_match_the_card(
    tiny_dataset, tmp_path
):
    """The ResNet-18's shipping path: float16 weights on disk, a float32 model when loaded,
    the card's test metrics and probe those of the loaded file; ``train`` takes the shipped
    file as finished (as ``train_models`` does with a copy)."""
    import torch

    from kpstudy.models.evaluation import evaluate
    from kpstudy.models.training import load_checkpoint, train
    from kpstudy.study.reproduction import probe_input, resnet_recipe, ship

    config = resnet_recipe(TINY)
    assert (config.backbone, config.epochs, config.images) == ("resnet18", 1, 4)
    path = tmp_path / "trained.pt"
    train(tiny_dataset, path, config, progress=False)
    target = tmp_path / "resnet18_quick.pt"
    card = ship(path, tiny_dataset, target, half=True)
    state = torch.load(target, weights_only=True)
    assert "optimizer" not in state and state["dataset"]["path"] is None
    floats = [v for v in state["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    assert json.loads(target.with_suffix(".json").read_text()) == card
    assert card["recipe"] == state["config"] and card["lineage"] == []
    backbone, _ = load_checkpoint(target)
    assert {p.dtype for p in backbone.state_dict().values() if p.is_floating_point()} == {
        torch.float32
    }
    summary, _ = evaluate(target, tiny_dataset, "test")
    pd.testing.assert_frame_equal(pd.DataFrame(card["test"]), summary)
    with torch.no_grad():
        h = backbone(probe_input(backbone.input_size)).double()
    assert h.shape[-1] == 256
    assert h.sum().item() == pytest.approx(card["probe"]["sum"], rel=1e-6, abs=1e-6)
    assert h.abs().sum().item() == pytest.approx(card["probe"]["abs_sum"], rel=1e-6)
    assert train(tiny_dataset, target, config, progress=False)["epoch"] == 1  # finished


def test_the_probe_input_is_the_same_fixed_ramp_at_any_size():
    import torch

    from kpstudy.study.reproduction import probe_input

    ramp = torch.linspace(0.0, 1.0, 3 * 64 * 64).reshape(1, 3, 64, 64).flip(-1)
    assert torch.equal(probe_input(), ramp)  # the friendly CNN's card's probe
    assert probe_input(256).shape == (1, 3, 256, 256)
    with pytest.raises(ValueError, match=r"^size: expected a positive integer, got 0$"):
        probe_input(0)


@pytest.fixture
def shipping(tiny_dataset, tmp_path, monkeypatch):
    """``train_models`` on the tiny dataset (``out/data``) with a stand-in ``train`` that
    records ``(checkpoint name, config)`` and writes nothing, and :data:`SHIPPED` pointed
    at ``tmp_path/shipped`` (empty). Returns ``(out, shipped folder, calls)``."""
    import shutil

    from kpstudy.models import training
    from kpstudy.study import reproduction as module

    out = tmp_path / "out"
    shutil.copytree(tiny_dataset, out / "data")
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    monkeypatch.setattr(module, "SHIPPED", {m: shipped / f"{m}.pt" for m in module.SHIPPED})
    calls = []

    def train(data_dir, out, config, **_):
        calls.append((Path(out).name, config))
        return {"model": {}}

    monkeypatch.setattr(training, "train", train)
    return out, shipped, calls


def _checkpoint(file: Path, config, data_dir: Path, **extra) -> bytes:
    """Write a checkpoint of ``config`` on ``data_dir``'s dataset, no weights; its bytes."""
    from dataclasses import asdict

    import torch

    from data_gen.dataset import load_coco

    dataset = dict(config=load_coco(data_dir)["info"]["config"], path=None)
    torch.save(dict(config=asdict(config), dataset=dataset, epoch=config.epochs, **extra), file)
    return file.read_bytes()


def test_train_models_copies_a_shipped_resnet_made_by_its_recipe(shipping):
    from kpstudy.study.reproduction import resnet_recipe, train_models

    out, shipped, calls = shipping
    config = resnet_recipe(TINY)
    made = _checkpoint(shipped / "resnet18.pt", config, out / "data")
    paths = train_models(TINY, out, progress=False)
    assert paths["resnet18"].read_bytes() == made  # train then finds it finished
    assert ("resnet18.pt", config) in calls
    assert not paths["cnn_patch_smooth"].exists()  # none shipped here: trained


@pytest.mark.parametrize(
    "change", [dict(resnet_epochs=2), dict(resnet_images=8), dict(precision="float32")]
)
def test_train_models_trains_a_resnet_whose_shipped_one_another_recipe_made(shipping, change):
    from kpstudy.study.reproduction import resnet_recipe, train_models

    out, shipped, calls = shipping
    _checkpoint(shipped / "resnet18.pt", resnet_recipe(replace(TINY, **change)), out / "data")
    (out / "models").mkdir()
    _checkpoint(
        out / "models" / "resnet18.pt", resnet_recipe(replace(TINY, **change)), out / "data"
    )
    paths = train_models(TINY, out, progress=False)
    assert not paths["resnet18"].exists()  # the other recipe's copy went; train writes none
    assert ("resnet18.pt", resnet_recipe(TINY)) in calls


def test_train_models_trains_a_resnet_on_another_dataset_than_the_shipped_ones(shipping):
    from kpstudy.study.reproduction import resnet_recipe, train_models

    out, shipped, calls = shipping
    _checkpoint(shipped / "resnet18.pt", resnet_recipe(TINY), out / "data")
    info = json.loads((out / "data" / "annotations.json").read_text())
    info["info"]["config"]["seed"] += 1
    (out / "data" / "annotations.json").write_text(json.dumps(info))
    assert not train_models(TINY, out, progress=False)["resnet18"].exists()


def test_retrain_trains_instead_of_copying_and_keeps_a_checkpoint_trained_here(shipping):
    from kpstudy.study.reproduction import resnet_recipe, train_models

    out, shipped, calls = shipping
    config = resnet_recipe(TINY)
    made = _checkpoint(shipped / "resnet18.pt", config, out / "data")
    path = train_models(TINY, out, progress=False)["resnet18"]
    assert path.read_bytes() == made
    train_models(TINY, out, progress=False, retrain=["resnet18"])
    assert not path.exists()  # the shipped copy went
    trained = _checkpoint(path, config, out / "data", optimizer={})
    train_models(TINY, out, progress=False, retrain=["resnet18"])
    assert path.read_bytes() == trained  # resumed, not begun again


@pytest.mark.parametrize("retrain", [("vgg",), ["resnet18", "cnn"], "resnet18"])
def test_retrain_names_only_models_that_ship(tmp_path, retrain):
    message = "retrain: expected some of cnn_patch_smooth, resnet18, got "
    with pytest.raises(ValueError, match=f"^{re.escape(message)}"):
        reproduce(TINY, tmp_path, retrain=retrain)
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(
    not SHIPPED["resnet18"].is_file(), reason="the trained ResNet-18 has not shipped yet"
)
def test_the_shipped_resnet_is_the_recipes_and_matches_its_card():
    import torch

    from kpstudy.models.training import config_of, load_checkpoint
    from kpstudy.study.reproduction import RESNET, probe_input, resnet_recipe

    shipped = SHIPPED["resnet18"]
    backbone, state = load_checkpoint(shipped)
    card = json.loads(shipped.with_suffix(".json").read_text())
    config = config_of(state)
    assert {k: getattr(config, k) for k in RESNET} == RESNET and config.images is None
    assert config == resnet_recipe(PROFILES["quick"])  # reproduce copies it
    friendly = json.loads(SHIPPED["cnn_patch_smooth"].with_suffix(".json").read_text())
    assert state["dataset"]["config"] == friendly["dataset"]["config"]  # the quick dataset
    assert card["recipe"] == state["config"] and card["dataset"] == state["dataset"]
    assert "optimizer" not in state and state["epoch"] == RESNET["epochs"]
    with torch.no_grad():
        h = backbone(probe_input(backbone.input_size)).double()
    assert h.sum().item() == pytest.approx(card["probe"]["sum"], rel=1e-5, abs=1e-3)
    assert h.abs().sum().item() == pytest.approx(card["probe"]["abs_sum"], rel=1e-5)


def test_a_notebook_kernels_own_stderr_goes_to_its_log_file(tmp_path):
    """IPKernel's log (what it prints when Ctrl-C stops a notebook, say) lands in the
    ``kernel_manager`` log; the cell's own output stays in the executed notebook."""
    script = f"""
from pathlib import Path
import nbformat, papermill
from kpstudy.study.reproduction import _ipc_kernel, kernel_manager
nb = nbformat.v4.new_notebook()
nb.cells = [nbformat.v4.new_code_cell(
    "get_ipython().kernel.log.error('kernel-side noise 7d1f'); print('cell output 7d1f')"
)]
folder = Path(r"{tmp_path}")
nbformat.write(nb, folder / "in.ipynb")
papermill.execute_notebook(
    str(folder / "in.ipynb"), str(folder / "out.ipynb"), kernel_name="python3",
    progress_bar=False, config=_ipc_kernel(str(folder)),
    kernel_manager_class=kernel_manager(folder / "kernel.log"),
)
"""
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    assert "kernel-side noise 7d1f" in (tmp_path / "kernel.log").read_text()
    assert "kernel-side noise 7d1f" not in run.stderr + run.stdout
    assert "cell output 7d1f" in (tmp_path / "out.ipynb").read_text()


def test_notebook_kernels_run_over_ipc_without_the_tcp_warning(tmp_path, capfd):
    import nbformat
    import papermill

    from kpstudy.study.reproduction import _ipc_kernel

    notebook = nbformat.v4.new_notebook()
    notebook.cells = [nbformat.v4.new_code_cell("x = 1"), nbformat.v4.new_code_cell("x * 2")]
    notebook.cells[0].metadata["tags"] = ["parameters"]
    notebook.metadata["kernelspec"] = {"name": "python3", "language": "python"}
    nbformat.write(notebook, tmp_path / "tiny.ipynb")
    sockets = tmp_path / "sockets"
    sockets.mkdir()
    papermill.execute_notebook(
        str(tmp_path / "tiny.ipynb"),
        str(tmp_path / "out.ipynb"),
        parameters={"x": 21},
        cwd=str(tmp_path),
        progress_bar=False,
        kernel_name="python3",
        config=_ipc_kernel(str(sockets)),
    )
    assert "eavesdropping" not in capfd.readouterr().err  # the kernel's own stderr too
    result = nbformat.read(tmp_path / "out.ipynb", as_version=4).cells[-1].outputs
    assert result[0]["data"]["text/plain"] == "42"
    assert not any(sockets.iterdir())  # the kernel's sockets are gone with it
    assert not list(tmp_path.glob("kernel-*"))


def test_ctrl_c_in_a_notebook_ends_with_one_line_and_no_traceback(tmp_path):
    """Ctrl-C (SIGINT to the process group, kernel included) while a cell runs: exit 130,
    ``kpstudy: interrupted`` and nothing else on stderr (not asyncio's report of the cell
    the interrupted kernel answered)."""
    import os
    import signal
    import time

    import nbformat

    notebook = nbformat.v4.new_notebook()
    started = tmp_path / "started"
    # a cell in compiled code sees Ctrl-C only when it returns to Python: a while later
    cell = f"""import signal, time
came = []
signal.signal(signal.SIGINT, lambda *_: came.append(time.monotonic()))
open(r'{started}', 'w').close()
while not came or time.monotonic() - came[0] < 2:
    time.sleep(0.05)
raise KeyboardInterrupt
"""
    notebook.cells = [nbformat.v4.new_code_cell(cell)]
    nbformat.write(notebook, tmp_path / "in.ipynb")
    script = f"""
import sys
from pathlib import Path
from kpstudy.cli import _interruptible
from kpstudy.study.reproduction import execute_notebook
folder = Path(r"{tmp_path}")
run = _interruptible(lambda argv: execute_notebook(
    folder / "in.ipynb", folder / "out.ipynb", {{}}, folder / "kernel.log", cwd=folder
))
sys.exit(run([]))
"""
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        # as in a terminal: a shell's background job (CI started with `&`) ignores SIGINT
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 600  # only a hang reaches it
    try:
        while not started.exists():
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "the cell never started (a hang)"
            time.sleep(0.1)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["kpstudy: interrupted"], err
