"""The README's worked example runs as written: its ``python -m kpstudy`` and
``python -m data_gen`` commands, on a tiny dataset laid out where the README expects the
quick study's (``results/quick/data``, ``results/quick/models/{cnn,cnn_patch_smooth}.pt``)."""

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from data_gen.perturb import make_perturbations
from kpstudy.models.training import TrainConfig, train

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_commands(text: str) -> list[list[str]]:
    """The ``.venv/bin/python -m kpstudy|data_gen …`` commands of the README's ``bash``
    blocks, continuation lines joined, as argument lists (``make`` lines, ``reproduce``
    and ``python -c`` scripts left out: CI and tests/kpstudy/study/test_reproduction.py
    run those)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if line.startswith((".venv/bin/python -m kpstudy ", ".venv/bin/python -m data_gen ")):
                words = shlex.split(line, comments=True)
                if words[3] != "reproduce":
                    commands.append(words)
    return commands


def test_the_readme_shows_the_worked_example():
    commands = readme_commands(README.read_text())
    subcommands = {tuple(c[2:4]) for c in commands}
    assert {
        ("kpstudy", "evaluate"),
        ("kpstudy", "campaign"),
        ("data_gen", "dataset"),
    } <= subcommands
    assert all(Path(c[0]).name == "python" for c in commands)


@pytest.fixture(scope="module")
def workspace(tiny_dataset, tmp_path_factory):
    """A folder laid out as after ``make reproduce``, at tiny scale."""
    root = tmp_path_factory.mktemp("readme")
    data = root / "results" / "quick" / "data"
    shutil.copytree(tiny_dataset, data)
    for kind in ("brightness", "objects"):
        make_perturbations(data, kind, seeds=2, seed=0, input_size=64)
    models = root / "results" / "quick" / "models"
    for name in ("cnn", "cnn_patch_smooth"):
        config = TrainConfig(backbone=name, epochs=1, batch_size=4, images=8, seed=1)
        train(data, models / f"{name}.pt", config, progress=False)
    return root


@pytest.mark.slow
def test_every_readme_command_runs_as_written(workspace):
    commands = readme_commands(README.read_text())
    assert commands
    for words in commands:
        argv = [sys.executable, *words[1:]]
        proc = subprocess.run(argv, cwd=workspace, capture_output=True, text=True, timeout=1200)
        assert proc.returncode == 0, f"{shlex.join(words)}\n{proc.stderr[-2000:]}"
    outputs = workspace / "results"
    assert (outputs / "example" / "brightness.sqlite").exists()
    assert (outputs / "example" / "objects.sqlite").exists()
    assert any((outputs / "mine" / "figures").iterdir())
