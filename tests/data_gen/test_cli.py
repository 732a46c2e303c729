"""data_gen.cli: ``python -m data_gen``'s commands refuse bad arguments and unusable
inputs with one line and nothing written, and write a dataset."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from data_gen.keypoints import KEYPOINT_NAMES
from tests.helpers.cli import assert_refused, run_cli


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--n", "0"], "n: expected a positive number"),
        (["--n", "2", "--size", "640by400"], "size: expected WIDTHxHEIGHT"),
        (["--n", "2", "--size", "8x8"], "size: expected width and height"),
        (["--n", "2", "--variant", "zeppelin"], "variant: unknown airplane variant 'zeppelin'"),
        (["--n", "2", "--workers", "0"], "workers: expected a positive integer"),
        (["--n", "2", "--mesh", "plane.obj"], "mesh, keypoints_json: expected both"),
    ],
)
def test_cli_rejects_bad_arguments_without_output(tmp_path, args, message):
    out = tmp_path / "out"
    run = subprocess.run(
        [sys.executable, "-m", "data_gen", "dataset", "--out", str(out), *args],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert message in run.stderr and "data_gen dataset: error:" in run.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_refuses_non_empty_or_unwritable_output(tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    run = subprocess.run(
        [sys.executable, "-m", "data_gen", "dataset", "--out", str(busy), "--n", "1"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and "out: directory" in run.stderr and "--overwrite" in run.stderr
    assert [p.name for p in busy.iterdir()] == ["keep.txt"]
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    run = subprocess.run(
        [sys.executable, "-m", "data_gen", "dataset", "--out", str(blocker / "data"), "--n", "1"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and "out: cannot write into" in run.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "busy"]


def test_cli_writes_a_dataset(tmp_path):
    out = tmp_path / "cli"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "data_gen",
            "dataset",
            "--out",
            str(out),
            "--n",
            "2",
            "--size",
            "96x60",
        ],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert "images/s" in run.stdout
    coco = json.loads((out / "annotations.json").read_text())
    assert len(coco["images"]) == 2 and coco["images"][0]["width"] == 96


def test_a_flat_single_triangle_mesh_is_refused_before_any_output(tmp_path):
    mesh = tmp_path / "triangle.obj"
    mesh.write_text("v -20 -20 0\nv 20 -20 0\nv 0 20 0\nf 1 2 3\n")
    # 23 distinct keypoints on the triangle: only the mesh is wrong
    keypoints = [
        {"name": name, "xyz": [-8 + 4 * (i % 5), -10 + 3 * (i // 5), 0]}
        for i, name in enumerate(KEYPOINT_NAMES)
    ]
    (tmp_path / "keypoints.json").write_text(json.dumps({"keypoints": keypoints}))
    work = tmp_path / "work"
    work.mkdir()
    proc = run_cli(
        "data_gen",
        "dataset",
        "--out",
        work / "o_mesh2",
        "--n",
        "2",
        "--size",
        "160x100",
        "--mesh",
        mesh,
        "--keypoints",
        tmp_path / "keypoints.json",
    )
    assert_refused(proc, "mesh_path:", "three dimensions")
    assert not any(work.iterdir())  # no .o_mesh2.partial/


def test_a_negative_seed_is_refused_before_any_output(tmp_path):
    proc = run_cli("data_gen", "dataset", "--out", tmp_path / "data", "--n", "2", "--seed", "-1")
    assert_refused(proc, "seed:", "non-negative")
    assert not any(tmp_path.iterdir())  # no .data.partial/
