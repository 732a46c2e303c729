"""kpstudy.study.reference: a run copied into a stamped reference folder."""

import json
import re
import subprocess
import sys

import pytest

from kpstudy.study.reference import log_stage, notebook_seconds, publish, run_log
from kpstudy.study.reproduction import compare_results, profile, reproduce


def _run(root):
    (root / "tables").mkdir(parents=True)
    (root / "figures").mkdir()
    (root / "notebooks").mkdir()
    (root / "campaigns").mkdir()
    (root / "REPORT.md").write_text("# report\n\n![t](figures/t.png)\n")
    (root / "tables" / "t.csv").write_text("status,time\nholds,1.5\n")
    (root / "tables" / "t.md").write_text("| status |\n")
    (root / "figures" / "t.png").write_bytes(b"\x89PNG")
    (root / "campaigns" / "t.sqlite").write_bytes(b"store")
    notebook = {"cells": [], "metadata": {"papermill": {"duration": 12.4}}}
    (root / "notebooks" / "06_local.ipynb").write_text(json.dumps(notebook))
    (root / "notebooks" / "07_global.ipynb").write_text(json.dumps({"metadata": {}}))
    return root


def test_publish_keeps_the_report_tables_and_figures_and_stamps_them(tmp_path):
    run = _run(tmp_path / "run")
    dest = publish(run, tmp_path / "ref", commit="7db18cb", command="kpstudy reproduce")
    kept = sorted(p.relative_to(dest).as_posix() for p in dest.rglob("*") if p.is_file())
    assert kept == ["REPORT.md", "STAMP.md", "figures/t.png", "tables/t.csv", "tables/t.md"]
    stamp = (dest / "STAMP.md").read_text()
    assert "`7db18cb`" in stamp and "`kpstudy reproduce`" in stamp
    assert "| 06_local | 12 |" in stamp and "07_global" not in stamp
    assert compare_results(dest, run) == {"tables/t.csv": "same"}
    assert notebook_seconds(run) == {"06_local": 12.4}


def test_publish_replaces_an_older_reference_whole(tmp_path):
    run = _run(tmp_path / "run")
    dest = tmp_path / "ref"
    (dest / "tables").mkdir(parents=True)
    (dest / "tables" / "old.csv").write_text("a\n1\n")
    publish(run, dest, commit="a" * 40, command="make reproduce")
    assert not (dest / "tables" / "old.csv").exists()
    assert not list(tmp_path.glob(".ref.partial"))


@pytest.mark.parametrize(
    "change, message",
    [
        ({"run": "missing"}, "run: expected a results folder with REPORT.md"),
        ({"commit": "HEAD"}, "commit: expected 7 to 40 hex digits"),
        ({"command": " "}, "command: expected the command line"),
    ],
)
def test_publish_refuses_bad_input_before_writing(tmp_path, change, message):
    run = _run(tmp_path / "run")
    args = {"run": run, "commit": "7db18cb", "command": "kpstudy reproduce"}
    if "run" in change:
        change = {"run": tmp_path / change["run"]}
    args.update(change)
    with pytest.raises(ValueError, match=message):
        publish(args.pop("run"), tmp_path / "ref", **args)
    assert not (tmp_path / "ref").exists()


def test_publish_cli_exits_2_with_one_line(tmp_path):
    run = _run(tmp_path / "run")
    cmd = [sys.executable, "-m", "kpstudy", "publish", str(run), str(tmp_path / "ref")]
    done = subprocess.run(
        [*cmd, "--commit", "main", "--command", "x"], capture_output=True, text=True
    )
    assert done.returncode == 2
    assert done.stderr.splitlines() == [
        "kpstudy publish: error: commit: expected 7 to 40 hex digits (git rev-parse), got 'main'"
    ]
    assert not (tmp_path / "ref").exists()
    done = subprocess.run(
        [*cmd, "--commit", "7db18cb", "--command", "x"], capture_output=True, text=True
    )
    assert done.returncode == 0 and (tmp_path / "ref" / "STAMP.md").is_file()


def test_each_stage_of_reproduce_is_logged_with_its_commit_and_command(tmp_path):
    out = reproduce(profile("quick"), tmp_path, stages=["report"], command="kpstudy reproduce")
    (entry,) = run_log(out)
    assert entry["stage"] == "report" and entry["finished"] and entry["seconds"] >= 0
    assert entry["command"] == "kpstudy reproduce" and len(entry["code"]) == 12
    assert entry["commit"] is None or re.fullmatch(r"[0-9a-f]{40}(\+changes)?", entry["commit"])
    log_stage(out, "notebooks", 7200.4, finished=False, command="kpstudy reproduce")
    assert [e["stage"] for e in run_log(out)] == ["report", "notebooks"]
    assert not run_log(out)[1]["finished"]


def test_publish_takes_the_commit_and_command_the_run_recorded(tmp_path, monkeypatch):
    run = _run(tmp_path / "run")
    monkeypatch.setattr("kpstudy.study.reference.code_commit", lambda: "a" * 40)
    for stage, seconds in (("notebooks", 3600.0), ("notebooks", 1800.0), ("report", 2.0)):
        log_stage(run, stage, seconds, finished=stage == "report", command="make reproduce")
    stamp = (publish(run, tmp_path / "ref") / "STAMP.md").read_text()
    assert f"- commit: `{'a' * 40}`" in stamp and "- command: `make reproduce`" in stamp
    assert "| notebooks | 5400 | 2 | 0 |" in stamp and "| total | 5402 |" in stamp
    assert not (tmp_path / "ref" / "runs.jsonl").exists()
    monkeypatch.setattr("kpstudy.study.reference.code_commit", lambda: "b" * 40 + "+changes")
    log_stage(run, "report", 1.0, finished=True, command="make reproduce")
    with pytest.raises(ValueError, match="commit: expected 7 to 40 hex digits"):
        publish(run, tmp_path / "ref2")  # two commits recorded, one of them with changes
    assert publish(run, tmp_path / "ref2", commit="c" * 7).is_dir()
