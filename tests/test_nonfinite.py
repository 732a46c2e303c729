"""Non-finite training (issue 29, point 5): ``--lr inf``, a NaN keypoint in the annotations,
a diverging loss and a NaN checkpoint are refused with one line; no NaN checkpoint is ever
written and the last good one is kept."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys

import pytest
import torch

from kpstudy.models import training as train_module
from kpstudy.models.data import load_keypoint_set
from kpstudy.models.evaluation import evaluate
from kpstudy.models.training import TrainConfig, TrainingDiverged, load_checkpoint, train

TINY = TrainConfig(epochs=2, batch_size=4, images=8, seed=1)  # 2 steps per epoch


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "kpstudy", *args], capture_output=True, text=True)


@pytest.mark.parametrize("name", ["lr", "sigma", "weight_decay", "dsnt_weight", "noise"])
def test_config_refuses_infinite_numbers(name):
    with pytest.raises(ValueError, match=f"^{name}: expected .*finite"):
        TrainConfig(**{name: math.inf})


def test_cli_train_lr_inf_exits_2_with_one_line_and_writes_nothing(tiny_dataset, tmp_path):
    proc = _cli(
        "train", "--data", str(tiny_dataset), "--out", str(tmp_path / "c.pt"), "--lr", "inf"
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "lr: expected a positive number (finite)" in proc.stderr
    assert "Traceback" not in proc.stderr and list(tmp_path.iterdir()) == []


@pytest.fixture
def nan_dataset(tiny_dataset, tmp_path):
    """The tiny dataset with one NaN coordinate in the first training image's keypoints."""
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    coco = json.loads((data / "annotations.json").read_text())
    image = next(im for im in coco["images"] if im["split"] == "train")
    annotation = next(a for a in coco["annotations"] if a["image_id"] == image["id"])
    annotation["keypoints"][3] = math.nan  # keypoint 1's u
    (data / "annotations.json").write_text(json.dumps(coco))
    return data, image["file_name"]


def test_a_nan_keypoint_is_refused_at_load_naming_the_image(nan_dataset, tmp_path):
    data, file_name = nan_dataset
    with pytest.raises(ValueError, match=f"^data: image '{file_name}' .*non-finite keypoints"):
        load_keypoint_set(data, "train", 64)
    with pytest.raises(ValueError, match="non-finite keypoints"):
        train(data, tmp_path / "c.pt", TINY, progress=False)
    assert not (tmp_path / "c.pt").exists()


def _nan_after(monkeypatch, calls: int):
    """Make the heatmap loss NaN from its ``calls + 1``-th evaluation on."""
    real, count = train_module.heatmap_loss, [0]

    def loss(*args, **kwargs):
        count[0] += 1
        value = real(*args, **kwargs)
        return value * math.nan if count[0] > calls else value

    monkeypatch.setattr(train_module, "heatmap_loss", loss)


def test_training_stops_at_the_first_nan_loss_and_keeps_the_last_good_checkpoint(
    tiny_dataset, tmp_path, monkeypatch
):
    out = tmp_path / "c.pt"
    _nan_after(monkeypatch, 3)  # epoch 1 (steps 1–2) and step 1 of epoch 2 are finite
    with pytest.raises(TrainingDiverged) as caught:
        train(tiny_dataset, out, TINY, progress=False)
    message = str(caught.value)
    assert message.startswith("lr: training diverged at epoch 2, step 2: the loss is nan")
    assert "\n" not in message and f"the checkpoint of epoch 1 at {out} is kept" in message
    state = torch.load(out, weights_only=True)
    assert state["epoch"] == 1
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())


def test_a_nan_first_epoch_writes_no_checkpoint(tiny_dataset, tmp_path, monkeypatch):
    _nan_after(monkeypatch, 0)
    with pytest.raises(TrainingDiverged, match="epoch 1, step 1: .* no checkpoint was written"):
        train(tiny_dataset, tmp_path / "c.pt", TINY, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_a_huge_lr_diverges_with_an_error_not_a_nan_checkpoint(tiny_dataset, tmp_path):
    config = TrainConfig(**(vars(TINY) | {"lr": 1e30}))
    with pytest.raises(TrainingDiverged, match="^lr: training diverged at epoch 1"):
        train(tiny_dataset, tmp_path / "c.pt", config, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def nan_checkpoint(tiny_dataset, tmp_path):
    """A finished checkpoint whose first weight tensor was then set to NaN."""
    path = tmp_path / "nan.pt"
    state = train(tiny_dataset, path, TrainConfig(**(vars(TINY) | {"epochs": 1})), progress=False)
    first = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][first] = torch.full_like(state["model"][first], math.nan)
    torch.save(state, path)
    return path


def test_a_nan_checkpoint_is_refused_by_evaluate_and_resume(nan_checkpoint, tiny_dataset):
    with pytest.raises(ValueError, match="^checkpoint: .* holds non-finite weights"):
        load_checkpoint(nan_checkpoint)
    with pytest.raises(ValueError, match="^checkpoint: .* holds non-finite weights"):
        evaluate(nan_checkpoint, tiny_dataset, "test")
    config = TrainConfig(**(vars(TINY) | {"epochs": 1}))
    with pytest.raises(ValueError, match="^out: .* holds non-finite weights"):
        train(tiny_dataset, nan_checkpoint, config, progress=False)


def test_cli_evaluate_of_a_nan_checkpoint_exits_2(nan_checkpoint, tiny_dataset, tmp_path):
    proc = _cli(
        "evaluate",
        "--checkpoint",
        str(nan_checkpoint),
        "--data",
        str(tiny_dataset),
        "--out",
        str(tmp_path / "eval"),
    )
    assert proc.returncode == 2 and "holds non-finite weights" in proc.stderr
    assert proc.stderr.count("\n") == 1 and not list(tmp_path.glob("eval*"))
