"""kpstudy.models.training on a tiny rendered dataset: targets, loss and PCK, the training
loop, checkpoints, resuming, fine-tuning stages and the train/evaluate commands; non-finite
training (issue 29, point 5): ``--lr inf``, a diverging loss and a NaN checkpoint are
refused with one line, no NaN checkpoint is ever written and the last good one is kept."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from kpstudy.models import training as train_module
from kpstudy.models.evaluation import evaluate
from kpstudy.models.training import (
    TrainConfig,
    TrainingDiverged,
    config_of,
    heatmap_loss,
    heatmap_targets,
    load_checkpoint,
    pck,
    train,
)
from tests.helpers.training import TINY


def test_gaussian_targets_sum_to_one_and_peak_at_the_keypoint():
    kp = torch.tensor([[[20.0, 30.0], [5.4, 60.2]]])
    g = heatmap_targets(kp, 64, sigma=1.0)
    torch.testing.assert_close(g.sum((-2, -1)), torch.ones(1, 2))
    flat = g.flatten(2).argmax(-1)
    assert (flat % 64).tolist() == [[20, 5]] and (flat // 64).tolist() == [[30, 60]]


def test_loss_is_zero_at_the_target_and_ignores_unweighted_keypoints():
    kp = torch.tensor([[[20.0, 30.0], [40.0, 10.0]]])
    logits = torch.log(heatmap_targets(kp, 64, 1.0).clamp_min(1e-30))
    ones, first = torch.ones(1, 2), torch.tensor([[1.0, 0.0]])
    assert heatmap_loss(logits, kp, ones, 1.0) < 1e-5
    wrong = logits.clone()
    wrong[0, 1] = logits[0, 0]  # channel 1 peaks at keypoint 0
    assert heatmap_loss(wrong, kp, ones, 1.0) > 1.0
    assert heatmap_loss(wrong, kp, first, 1.0) < 1e-5
    assert heatmap_loss(wrong, kp, ones, 1.0, dsnt_weight=1.0) > heatmap_loss(wrong, kp, ones, 1.0)


def test_pck_counts_weighted_keypoints():
    truth = np.zeros((1, 4, 2))
    pred = np.array([[[0.5, 0], [1.5, 0], [3, 0], [9, 9]]])
    out = pck(pred, truth, np.array([[1, 1, 1, 0]]))
    assert out == {"pck@1": 1 / 3, "pck@2": 2 / 3, "pck@4": 1.0, "mean_error": 5 / 3}


def test_training_lowers_the_loss_and_writes_a_checkpoint(checkpoint):
    backbone, state = load_checkpoint(checkpoint)
    losses = [row["loss"] for row in state["history"]]
    assert len(losses) == 3 and losses[-1] < losses[0]
    assert state["config"] == vars(TINY) | {} and state["epoch"] == 3
    assert {"val_pck@2", "val_mean_error", "seconds"} <= set(state["history"][-1])
    assert not backbone.training
    for key, value in backbone.state_dict().items():
        assert torch.equal(value, state["model"][key])


def test_a_finished_checkpoint_is_returned_and_another_config_refused(checkpoint, tiny_dataset):
    before = checkpoint.read_bytes()
    state = train(tiny_dataset, checkpoint, TINY, progress=False)
    assert state["epoch"] == 3 and checkpoint.read_bytes() == before
    with pytest.raises(ValueError, match=r"another configuration \(epochs differ\)"):
        train(tiny_dataset, checkpoint, TrainConfig(**(vars(TINY) | {"epochs": 5})))


def test_an_interrupted_run_resumes_to_the_same_weights(tiny_dataset, tmp_path, monkeypatch):
    config = TrainConfig(**(vars(TINY) | {"epochs": 2}))
    whole = train(tiny_dataset, tmp_path / "whole.pt", config, progress=False)

    save = train_module._save

    def save_then_crash(path, state):
        save(path, state)
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "_save", save_then_crash)
    with pytest.raises(KeyboardInterrupt):
        train(tiny_dataset, tmp_path / "cut.pt", config, progress=False)
    monkeypatch.setattr(train_module, "_save", save)
    assert torch.load(tmp_path / "cut.pt", weights_only=True)["epoch"] == 1
    resumed = train(tiny_dataset, tmp_path / "cut.pt", config, progress=False)
    assert [r["loss"] for r in resumed["history"]] == [r["loss"] for r in whole["history"]]
    for key, value in whole["model"].items():
        torch.testing.assert_close(resumed["model"][key], value)


@pytest.mark.parametrize(
    "content, message",
    [(b"not a checkpoint", "checkpoint: cannot read"), (None, "checkpoint: no file")],
)
def test_bad_checkpoints_are_named(tmp_path, content, message):
    path = tmp_path / "bad.pt"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        load_checkpoint(path)


def test_bad_config_is_named():
    with pytest.raises(ValueError, match="backbone: expected one of"):
        TrainConfig(backbone="vgg")
    with pytest.raises(ValueError, match="epochs: expected a positive integer"):
        TrainConfig(epochs=0)
    with pytest.raises(ValueError, match="sigma: expected a positive number"):
        TrainConfig(sigma=0.0)
    with pytest.raises(ValueError, match="precision: expected one of"):
        TrainConfig(precision="float16")


def test_the_command_line_offers_every_config_field_with_its_default(monkeypatch):
    """``train``'s options are TrainConfig's fields, typed and with its defaults; ``--init``
    (a checkpoint, not its digest) and ``--certified-weight`` (``--certified``'s weight
    unless given) are the command line's own."""
    from dataclasses import fields

    from kpstudy import cli

    parsed = []
    monkeypatch.setattr(cli, "_train", parsed.append)
    assert cli.main(["train", "--data", "d", "--out", "o.pt"]) == 0
    for f in fields(TrainConfig):
        if f.name not in ("init", "certified_weight"):
            assert getattr(parsed[-1], f.name) == f.default, f.name
    assert parsed[-1].certified_weight is None and parsed[-1].init_checkpoint is None
    chosen = ["--epochs", "3", "--lr", "0.5", "--certified-ramp", "2", "--schedule", "constant"]
    cli.main(["train", "--data", "d", "--out", "o.pt", *chosen])
    args = parsed[-1]
    assert (args.epochs, args.lr, args.certified_ramp, args.schedule) == (3, 0.5, 2, "constant")


def test_a_bfloat16_run_trains_float32_weights(checkpoint, tiny_dataset, tmp_path):
    config = TrainConfig(**(vars(TINY) | {"precision": "bfloat16"}))
    state = train(tiny_dataset, tmp_path / "bf16.pt", config, progress=False)
    losses = [row["loss"] for row in state["history"]]
    assert losses[-1] < losses[0]
    float32 = torch.load(checkpoint, weights_only=True)["model"]
    assert all(v.dtype == float32[k].dtype for k, v in state["model"].items())
    assert any(not torch.equal(v, float32[k]) for k, v in state["model"].items())
    backbone, loaded = load_checkpoint(tmp_path / "bf16.pt")
    assert loaded["config"]["precision"] == "bfloat16"


def test_a_checkpoint_from_before_precision_reads_as_float32(checkpoint):
    state = torch.load(checkpoint, weights_only=True)
    del state["config"]["precision"]
    assert config_of(state) == TINY


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "kpstudy", *args], capture_output=True, text=True)


def test_cli_train_and_evaluate(tiny_dataset, tmp_path):
    ckpt = tmp_path / "c.pt"
    proc = _cli(
        "train",
        "--data",
        str(tiny_dataset),
        "--epochs",
        "1",
        "--images",
        "4",
        "--batch-size",
        "4",
        "--out",
        str(ckpt),
        "--threads",
        "1",
    )
    assert proc.returncode == 0, proc.stderr
    assert '"epoch": 1' in proc.stdout and ckpt.is_file()
    proc = _cli(
        "evaluate",
        "--checkpoint",
        str(ckpt),
        "--data",
        str(tiny_dataset),
        "--out",
        str(tmp_path / "eval"),
    )
    assert proc.returncode == 0, proc.stderr
    assert "pck@2" in (tmp_path / "eval.md").read_text()
    assert (tmp_path / "eval_images.csv").is_file()


@pytest.mark.parametrize(
    "args, message",
    [
        (["train", "--data", "nowhere", "--out", "{tmp}/x.pt"], "data: no dataset folder"),
        (
            ["train", "--data", "{data}", "--out", "{tmp}/x.pt", "--backbone", "vgg"],
            "backbone: expected",
        ),
        (["train", "--data", "{data}", "--out", "{tmp}/x.pt", "--epochs", "0"], "epochs: expected"),
        (["evaluate", "--checkpoint", "{tmp}/none.pt", "--data", "{data}"], "checkpoint: no file"),
    ],
)
def test_cli_bad_input_exits_2_and_writes_nothing(tiny_dataset, tmp_path, args, message):
    args = [a.format(tmp=tmp_path, data=tiny_dataset) for a in args]
    proc = _cli(*args)
    assert proc.returncode == 2 and message in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_fine_tuning_stage_starts_from_its_initial_checkpoint(checkpoint, tiny_dataset, tmp_path):
    from kpstudy.models.training import weights_digest

    _, base = load_checkpoint(checkpoint)
    digest = weights_digest(base["model"])
    # lr so small that the weights stay where the first stage left them
    stage = TrainConfig(
        epochs=1, batch_size=4, images=8, lr=1e-12, schedule="constant", init=digest
    )
    state = train(tiny_dataset, tmp_path / "ft.pt", stage, init=checkpoint, progress=False)
    assert state["lineage"] == [base["config"]]
    for name, value in base["model"].items():
        if value.is_floating_point() and "running_" not in name:  # batch statistics move
            torch.testing.assert_close(state["model"][name], value, atol=1e-6, rtol=0)
    assert [g["lr"] for g in torch.load(tmp_path / "ft.pt")["optimizer"]["param_groups"]] == [1e-12]
    third = replace(stage, init=weights_digest(state["model"]))  # a stage on the stage
    again = train(tiny_dataset, tmp_path / "ft2.pt", third, init=tmp_path / "ft.pt", progress=False)
    assert again["lineage"] == [base["config"], state["config"]]
    scratch = train(
        tiny_dataset,
        tmp_path / "scratch.pt",
        TrainConfig(**(vars(stage) | {"init": None})),
        progress=False,
    )
    assert any(
        not torch.equal(scratch["model"][k], v)
        for k, v in base["model"].items()
        if v.is_floating_point()
    )


def test_a_fine_tuning_stage_refuses_other_weights(checkpoint, tiny_dataset, tmp_path):
    stage = TrainConfig(epochs=1, batch_size=4, images=8, schedule="constant", init="0" * 64)
    with pytest.raises(ValueError, match="init: .* digest .* expected 000000000000"):
        train(tiny_dataset, tmp_path / "a.pt", stage, init=checkpoint, progress=False)
    with pytest.raises(ValueError, match="init: expected the checkpoint"):
        train(tiny_dataset, tmp_path / "b.pt", stage, progress=False)
    with pytest.raises(ValueError, match="init: given, but"):
        train(tiny_dataset, tmp_path / "c.pt", TINY, init=checkpoint, progress=False)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("schedule", "cosine", "schedule: expected one of"),
        ("init", "abc", "init: expected a SHA-256"),
        ("certified_scale_from", 0.5, "certified_scale_from: expected at most"),
        ("certified_scale_from", -0.1, "certified_scale_from: expected a number"),
    ],
)
def test_bad_fine_tuning_settings_are_named(field, value, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(certified_scale=0.25, **{field: value})


def test_the_term_grows_from_its_first_scale(tiny_dataset, tmp_path, monkeypatch):
    scales = []

    def record(self, x, keypoints, weights, scale):
        scales.append(scale)
        return 0 * sum(p.sum() for p in self.backbone.parameters())

    monkeypatch.setattr(train_module._CertifiedTerm, "__call__", record)
    config = TrainConfig(
        "cnn_affine",
        epochs=2,
        batch_size=4,
        images=8,
        certified_weight=1.0,
        certified_start=0,
        certified_ramp=2,
        certified_scale_from=0.1,
        certified_scale=0.5,
    )
    train(tiny_dataset, tmp_path / "c.pt", config, progress=False)
    expected = [0.1 + 0.4 * (step / 4) ** 2 for step in range(4)]
    assert scales == pytest.approx(expected)


SHORT = TrainConfig(epochs=2, batch_size=4, images=8, seed=1)  # 2 steps per epoch


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
        train(tiny_dataset, out, SHORT, progress=False)
    message = str(caught.value)
    assert message.startswith("lr: training diverged at epoch 2, step 2: the loss is nan")
    assert "\n" not in message and f"the checkpoint of epoch 1 at {out} is kept" in message
    state = torch.load(out, weights_only=True)
    assert state["epoch"] == 1
    assert all(torch.isfinite(v).all() for v in state["model"].values() if v.is_floating_point())


def test_a_nan_first_epoch_writes_no_checkpoint(tiny_dataset, tmp_path, monkeypatch):
    _nan_after(monkeypatch, 0)
    with pytest.raises(TrainingDiverged, match="epoch 1, step 1: .* no checkpoint was written"):
        train(tiny_dataset, tmp_path / "c.pt", SHORT, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_a_huge_lr_diverges_with_an_error_not_a_nan_checkpoint(tiny_dataset, tmp_path):
    config = TrainConfig(**(vars(SHORT) | {"lr": 1e30}))
    with pytest.raises(TrainingDiverged, match="^lr: training diverged at epoch 1"):
        train(tiny_dataset, tmp_path / "c.pt", config, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def nan_checkpoint(tiny_dataset, tmp_path):
    """A finished checkpoint whose first weight tensor was then set to NaN."""
    path = tmp_path / "nan.pt"
    state = train(tiny_dataset, path, TrainConfig(**(vars(SHORT) | {"epochs": 1})), progress=False)
    first = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][first] = torch.full_like(state["model"][first], math.nan)
    torch.save(state, path)
    return path


def test_a_nan_checkpoint_is_refused_by_evaluate_and_resume(nan_checkpoint, tiny_dataset):
    with pytest.raises(ValueError, match="^checkpoint: .* holds non-finite weights"):
        load_checkpoint(nan_checkpoint)
    with pytest.raises(ValueError, match="^checkpoint: .* holds non-finite weights"):
        evaluate(nan_checkpoint, tiny_dataset, "test")
    config = TrainConfig(**(vars(SHORT) | {"epochs": 1}))
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
