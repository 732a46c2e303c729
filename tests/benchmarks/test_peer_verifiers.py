"""benchmarks/peer_verifiers.py without the peers: a stand-in verifier (a shell script in
the place of their interpreters) answers each instance of a small fake benchmark by its
name, so that the answers' mapping, the summary, the wall-clock kill and the refusal of
bad input are checked in seconds."""

import json
import stat

import numpy as np
import pytest

from benchmarks import peer_verifiers
from kpstudy.verify.export import read_answer

#: The stand-in: reads the instance from --net / --onnx_path, writes its answer to
#: --result_file / --results_file, and leaves a parse cache beside --vnnlib_path as
#: α,β-CROWN does.
FAKE_PEER = """#!/bin/bash
while [ $# -gt 0 ]; do
  case $1 in
    --net|--onnx_path) net=$(basename "$2"); shift;;
    --result_file|--results_file) result=$2; shift;;
    --vnnlib_path) touch "$2.compiled"; shift;;
  esac
  shift
done
case $net in
  sat.onnx) printf 'sat\\n((X_0  0.25)\\n(X_1  0.5)\\n(Y_0  -1.0))\\n' > "$result";;
  unsat.onnx) echo unsat > "$result";;
  timeout.onnx) echo timeout > "$result";;
  crash.onnx) echo "it failed to load" >&2; exit 1;;
  hang.onnx) exec sleep 60;;
esac
"""
#: Instance → kpstudy's verdict in reference.csv.
REFERENCE = {
    "sat": "violated",
    "unsat": "violated",
    "timeout": "holds",
    "crash": "unknown",
    "hang": "holds",
}


@pytest.fixture
def bench(tmp_path):
    folder = tmp_path / "bench"
    for sub in ("onnx", "vnnlib"):
        (folder / sub).mkdir(parents=True)
    rows, reference = [], ["name,status,time,nodes,method,max_nodes"]
    for i, (name, status) in enumerate(REFERENCE.items(), 1):
        (folder / "onnx" / f"{name}.onnx").write_text("")
        (folder / "vnnlib" / f"{name}.vnnlib").write_text("")
        rows.append(f"onnx/{name}.onnx,vnnlib/{name}.vnnlib,60")
        reference.append(f"{name},{status},{i}.000,1,auto,20")
    (folder / "instances.csv").write_text("\n".join(rows) + "\n")
    (folder / "reference.csv").write_text("\n".join(reference) + "\n")
    fake = tmp_path / "fake_python"
    fake.write_text(FAKE_PEER)
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    config, script = tmp_path / "base.yaml", tmp_path / "abcrown.py"
    config.write_text("general:\n  device: cpu\n")
    script.write_text("")
    return folder, fake, config, script


def test_answers_map_to_kpstudys_words(tmp_path):
    assert [peer_verifiers.verdict(a) for a in ("unsat", "sat", "timeout", "early_stop", "")] == [
        "holds",
        "violated",
        "unknown",
        "unknown",
        "unknown",
    ]
    neuralsat, abcrown, empty = tmp_path / "n.txt", tmp_path / "a.txt", tmp_path / "e.txt"
    neuralsat.write_text("sat\n((X_1 0.5)\n(X_0 0.25)\n(Y_0 -1.0))\n")
    abcrown.write_text("sat\n((X_0  0.25)\n(X_1  0.5)\n(Y_0  -1.0))")
    empty.write_text("")
    for path in (neuralsat, abcrown):
        status, x = read_answer(path)
        assert status == "sat" and np.array_equal(x, [0.25, 0.5])
    assert read_answer(empty) == ("", None)


def test_both_peers_beside_the_reference(bench, tmp_path, capsys):
    folder, fake, config, script = bench
    out = tmp_path / "out"
    result = peer_verifiers.main(
        [str(folder), "--timeout", "1", "--grace", "0.5", "--neuralsat-python", str(fake)]
        + ["--abcrown", str(script), "--abcrown-python", str(fake)]
        + ["--abcrown-config", str(config), "--out", str(out)]
    )
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == result
    assert json.loads((out / "peer_verifiers.json").read_text()) == result
    assert not list((folder / "vnnlib").glob("*.compiled"))  # α,β-CROWN read a copy
    for peer in ("neuralsat", "abcrown"):
        summary, rows = result["peers"][peer]["summary"], result["peers"][peer]["rows"]
        assert [r["verdict"] for r in rows] == ["violated", "holds"] + ["unknown"] * 3
        assert [r["answer"] for r in rows] == ["sat", "unsat", "timeout", "error", "killed"]
        assert rows[0]["x"] == [0.25, 0.5]
        assert rows[0]["counterexample"].startswith("not checked: no README.md")
        assert rows[3]["log"][-1] == "it failed to load" and rows[3]["exit"] == 1
        assert rows[4]["killed"] and 1.5 <= rows[4]["seconds"] < 10
        assert {k: summary[k] for k in ("instances", "loaded", "decided", "holds")} == {
            "instances": 5,
            "loaded": 3,
            "decided": 2,
            "holds": 1,
        }
        assert (summary["violated"], summary["unknown"], summary["agreeing"]) == (1, 3, 1)
        assert summary["disagreeing"] == ["unsat"]
        assert (summary["errors"], summary["killed"]) == (["crash"], ["hang"])
        assert summary["decided_within_timeout"] == 2
        assert (summary["kpstudy_median_s"], summary["kpstudy_max_s"]) == (3.0, 5.0)
        assert summary["speed_ratio"] == round(summary["median_s"] / 3.0, 2)
        assert summary["counterexamples"] == {"given": 1, "checked": 0, "real": 0, "not_real": []}


@pytest.mark.parametrize(
    "change, message",
    [
        ("no reference", "folder: no reference.csv in"),
        ("abcrown alone", "abcrown-python: required with --abcrown"),
        ("peers", "peers: abcrown is not available: no --abcrown given"),
        ("missing file", "instances.csv: line 1: no file"),
    ],
)
def test_bad_input_is_one_line(bench, capsys, change, message):
    folder, fake, _, script = bench
    argv = [str(folder), "--neuralsat-python", str(fake)]
    if change == "no reference":
        (folder / "reference.csv").unlink()
    elif change == "abcrown alone":
        argv += ["--abcrown", str(script)]
    elif change == "peers":
        argv += ["--peers", "abcrown"]
    else:
        (folder / "onnx" / "sat.onnx").unlink()
    with pytest.raises(SystemExit) as ended:
        peer_verifiers.main(argv)
    err = capsys.readouterr().err
    assert ended.value.code == 2 and err.count("\n") == 1
    assert err.startswith(f"peer_verifiers: error: {message}"), err
