"""The runnable examples of docs/examples run as written and print their verdicts (each in
its own process, from the repository root, as their docstrings say to run them)."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "docs" / "examples"


def run_example(name: str, *args: str) -> list[str]:
    """Run ``docs/examples/<name>`` with this interpreter; its stdout lines."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    env.setdefault("OMP_NUM_THREADS", "1")
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_every_example_has_a_test_here():
    assert {p.name for p in EXAMPLES.glob("*.py")} == {"own_model.py", "export_vnnlib.py"}


def test_own_model_goes_from_a_network_and_a_hull_to_verdicts():
    lines = run_example("own_model.py")
    assert len(lines) == 2, lines
    assert re.fullmatch(r"verify: holds \(\d+ nodes\)", lines[0]), lines
    assert lines[1] == "certify: allocation method holds, pose-bound method holds", lines


def test_export_writes_an_instance_that_onnxruntime_runs(tmp_path):
    lines = run_example("export_vnnlib.py", str(tmp_path))
    assert lines[0] == (
        f"wrote {tmp_path / 'model.onnx'} (3 inputs, 6 outputs) and "
        f"{tmp_path / 'spec.vnnlib'} (6 disjuncts)"
    ), lines
    assert re.fullmatch(
        r"onnxruntime on 64 points of the box: least margin \S+, every keypoint kept", lines[1]
    ), lines
    assert (tmp_path / "model.onnx").stat().st_size > 0
    assert "(declare-const X_2 Real)" in (tmp_path / "spec.vnnlib").read_text()


def test_the_docs_relative_links_resolve():
    """docs/results.md, the log and the examples' README link files that exist."""
    pages = [ROOT / "docs" / "results.md", EXAMPLES / "README.md"]
    pages += sorted((ROOT / "docs" / "log").glob("*.md"))
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target:
                assert (page.parent / target).exists(), f"{page.relative_to(ROOT)}: {target}"
