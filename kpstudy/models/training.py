"""Training a heatmap backbone on data_gen's dataset (paper §8.1).

Targets are Gaussians (kornia ``render_gaussian2d``, σ in heatmap pixels) normalised to
sum 1; the loss is the cross-entropy of the network's spatial softmax against them (the
target head's softmax is trained directly), minus the target's entropy so that a perfect
fit scores 0 (a KL divergence), optionally plus ``dsnt_weight`` × the mean Euclidean
error of the DSNT keypoints in heatmap pixels. Keypoints outside the image are left out.
Augmentation keeps the keypoint geometry: colour jitter and Gaussian noise (kornia).
AdamW with a one-cycle schedule (``schedule='onecycle'``) or a constant learning rate
(``'constant'``, for fine-tuning).

A run may start from another checkpoint's weights (``init``: the SHA-256 of those weights,
:func:`weights_digest`; :func:`train` takes the checkpoint's path and checks it), e.g. a
second, certified stage on top of a natural or lightly certified one. The checkpoint
records the configurations of every stage before it (``lineage``, earliest first: the
initial checkpoint's own lineage, then its configuration).

With ``certified_weight`` > 0 a bound term (:mod:`kpstudy.models.certified`) joins the loss:
the heatmap loss's worst case, bounded by kpstudy.verify's forward bounds over random
hulls of the study's kinds around the first ``certified_hulls`` images of each batch.
Its gradient is rescaled to ``certified_weight`` times the natural loss's gradient norm
(``_backward()``), so that it shapes the network without swamping the natural term.
The term starts after ``certified_start`` natural epochs and its hulls grow from
``certified_scale_from`` (0: the image itself) to ``certified_scale`` × their full size
over ``certified_ramp`` epochs, quadratically in time (the warm-up of certified training:
slow while the bounds are loosest). A scale below 1 bounds sub-hulls around the image,
as SABR (Müller et al. 2023) bounds small boxes: a weaker term that costs less accuracy
and, measured here, still tightens the bounds over the whole hulls.

With ``stability_weight`` > 0 a second term joins from the first epoch: the first
layer's ReLU instability (:func:`kpstudy.models.certified.relu_instability`) over a
random brightness or contrast hull around every image of the batch, exact because the
layer is affine, its gradient rescaled the same way. Those hulls change every pixel a
little, and each first-layer ReLU they can flip costs the verifier an error symbol that
later layers widen (a brightness step flips 7.5× as many first-layer ReLUs of the friendly
CNN as of the natural one). With ``stability_hulls='blocks'`` the term's hulls are random
block hulls instead (the image and four copies with a 3×3 block of random values,
:func:`kpstudy.models.certified.block_hull_points`) around the first
:data:`BLOCK_STABILITY_HULLS` images of a batch, and it reads *every* ReLU: each one's band
is the range of its input over the hull's five vertices and a random interior point,
passed through the backbone as one more batch. Past the first layer that band is sampled,
a lower estimate of the one the verifier bounds; the term pushes the ReLUs that a block
really flips out of their band (Xiao et al. 2019's ReLU stability). A 3×3 block flips
thousands of ReLUs in every layer of ResNet-18.

A checkpoint (``torch.save``, written atomically after every epoch) holds the
configuration, the dataset's description, the model, optimiser and scheduler states and
the metric history; training again with the same configuration resumes from it.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import numbers
import re
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import kornia.augmentation as KA
import numpy as np
import torch
from kornia.geometry.subpix import render_gaussian2d
from torch import nn
from tqdm import tqdm

from kpstudy import _checks
from kpstudy.io import write_bytes_atomic
from kpstudy.models.backbones import BACKBONES, build_backbone
from kpstudy.models.data import KeypointSet, load_keypoint_set
from kpstudy.models.heads import argmax_keypoints, dsnt_keypoints
from kpstudy.models.preprocess import to_model_input

FORMAT = "kpstudy-checkpoint/1"
#: Learning-rate schedules of :class:`TrainConfig`.
SCHEDULES = ("onecycle", "constant")
#: Forward-pass precisions of :class:`TrainConfig` (``'bfloat16'``: autocast).
PRECISIONS = ("float32", "bfloat16")
#: Hulls of the stability term (:class:`TrainConfig`'s ``stability_hulls``).
STABILITY_HULLS = ("photometric", "blocks")
#: Images of a batch that get a block hull in the ``'blocks'`` stability term (six points
#: each through the backbone: a ResNet-18 epoch of batches of 32 takes about twice as long).
BLOCK_STABILITY_HULLS = 4
#: The bound term's weight of ``train --certified`` (the verification-friendly CNN's).
CERTIFIED_WEIGHT = 2.0


#: The argument group of the certified-training options (``python -m kpstudy train``).
CERTIFIED_GROUP = "certified training (a bound term over random hulls)"


def _option(default, help: str, group: str | None = None):
    """A :class:`TrainConfig` field and its command-line help (``python -m kpstudy train``
    offers every field that has one, a ``group``'s in that argument group)."""
    return field(default=default, metadata={"help": help, "group": group})


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (stored in the checkpoint).

    ``images``: use at most this many training images (``None``: all).
    ``sigma``: target Gaussian std, heatmap pixels. ``jitter``: brightness, contrast and
    saturation jitter strength. ``noise``: Gaussian noise std on the [0, 1] input.
    ``certified_*``: the bound term (module docstring); ``certified_weight`` is the norm of
    its gradient as a fraction of the natural loss's gradient norm; 0 trains naturally.
    ``stability_weight``: the same share for a ReLU stability term (module docstring); 0
    leaves it out. ``stability_hulls``: its hulls, ``'photometric'`` (brightness and
    contrast, the first layer, exact) or ``'blocks'`` (3×3 blocks, every ReLU, sampled).
    ``schedule``: ``'onecycle'`` (peak ``lr``) or ``'constant'``. ``precision``: the
    forward pass of the natural loss in ``'float32'`` or under ``'bfloat16'`` autocast
    (weights, optimiser and loss stay float32; ~1.8× faster steps on a CPU with AVX-512
    BF16, same test accuracy); the bound term always runs in float32. ``init``: the
    :func:`weights_digest` of the checkpoint whose weights start the run (``None``: a
    random initialisation from ``seed``).
    """

    backbone: str = _option("cnn", "cnn, cnn_affine, cnn_patch, cnn_patch_smooth or resnet18")
    epochs: int = _option(20, "training epochs")
    batch_size: int = _option(32, "images per batch")
    lr: float = _option(3e-3, "peak learning rate")
    weight_decay: float = _option(1e-4, "AdamW weight decay")
    sigma: float = _option(1.0, "target std, heatmap px")
    dsnt_weight: float = _option(0.05, "weight of the DSNT keypoints' error, heatmap px")
    jitter: float = _option(0.2, "brightness, contrast and saturation jitter strength")
    noise: float = _option(0.02, "Gaussian noise std on the [0, 1] input")
    images: int | None = _option(None, "use at most this many training images")
    seed: int = _option(0, "random seed")
    certified_weight: float = 0.0
    certified_hulls: int = _option(8, "hulls per batch", CERTIFIED_GROUP)
    certified_start: int = _option(1, "natural epochs before the term", CERTIFIED_GROUP)
    certified_ramp: int = _option(
        4, "epochs over which the hulls grow to full size", CERTIFIED_GROUP
    )
    certified_scale: float = _option(
        1.0,
        "the hulls' final size, a fraction of the full hull (SABR-style sub-hulls)",
        CERTIFIED_GROUP,
    )
    certified_method: str = _option(
        "zonotope",
        "the term's bounds: zonotope (the verifier's) or forward (cheaper, looser)",
        CERTIFIED_GROUP,
    )
    certified_scale_from: float = _option(
        0.0, "the hulls' size when the term starts (0: the image itself)", CERTIFIED_GROUP
    )
    stability_weight: float = _option(
        0.0,
        "share of a ReLU stability term over the --stability-hulls (0: none)",
    )
    stability_hulls: str = _option(
        "photometric",
        "the stability term's hulls: photometric (the first layer, exact) or blocks (every "
        "ReLU over 3x3-block hulls, sampled)",
    )
    schedule: str = _option("onecycle", "onecycle or constant learning rate")
    init: str | None = None
    precision: str = _option(
        "float32", "forward pass of the natural loss: float32 or bfloat16 (autocast)"
    )

    def __post_init__(self) -> None:
        _checks.choice(self.backbone, "backbone", sorted(BACKBONES))
        for name in ("epochs", "batch_size", "certified_hulls", "certified_ramp"):
            _checks.integer(getattr(self, name), name, minimum=1)
        _checks.integer(self.images, "images", minimum=1, optional=True)
        from kpstudy.models.certified import BOUND_METHODS

        _checks.choice(self.certified_method, "certified_method", BOUND_METHODS)
        if not 0 < self.certified_scale <= 1:
            raise ValueError(
                f"certified_scale: expected a number in (0, 1], got {self.certified_scale!r}"
            )
        if not (_finite(self.certified_scale_from) and 0 <= self.certified_scale_from):
            raise ValueError(
                "certified_scale_from: expected a number in [0, certified_scale], got "
                f"{self.certified_scale_from!r}"
            )
        if self.certified_scale_from > self.certified_scale:
            raise ValueError(
                f"certified_scale_from: expected at most certified_scale={self.certified_scale}, "
                f"got {self.certified_scale_from!r}"
            )
        _checks.choice(self.schedule, "schedule", SCHEDULES)
        _checks.choice(self.stability_hulls, "stability_hulls", STABILITY_HULLS)
        _checks.choice(self.precision, "precision", PRECISIONS)
        if self.init is not None and not (
            isinstance(self.init, str) and re.fullmatch(r"[0-9a-f]{64}", self.init)
        ):
            raise ValueError(
                f"init: expected a SHA-256 hex digest of a checkpoint's weights, got {self.init!r}"
            )
        for name in ("lr", "sigma"):
            if not (_finite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(
                    f"{name}: expected a positive number (finite), got {getattr(self, name)!r}"
                )
        _checks.integer(self.certified_start, "certified_start", minimum=0)
        for name in (
            "weight_decay",
            "dsnt_weight",
            "jitter",
            "noise",
            "certified_weight",
            "stability_weight",
        ):
            if not (_finite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(
                    f"{name}: expected a number >= 0 (finite), got {getattr(self, name)!r}"
                )


class TrainingDiverged(ValueError):
    """The training loss became NaN or infinite; the checkpoint on disk is the last good one."""


def _finite(x) -> bool:
    return isinstance(x, numbers.Real) and math.isfinite(x)


def _finite_state(model: dict) -> bool:
    """Whether every floating-point tensor of a model state dict is finite."""
    return all(bool(torch.isfinite(v).all()) for v in model.values() if v.is_floating_point())


def heatmap_targets(keypoints: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Gaussian target distributions ``(B, K, size, size)`` (each sums to 1) centred at
    ``keypoints`` ``(B, K, 2)`` given as ``(u, v)`` heatmap pixels."""
    std = torch.full_like(keypoints, float(sigma))
    g = render_gaussian2d(keypoints, std, (size, size), normalized_coordinates=False)
    return g / g.sum((-2, -1), keepdim=True).clamp_min(1e-30)


def heatmap_loss(heatmaps, keypoints, weights, sigma: float, dsnt_weight: float = 0.0):
    """Mean over weighted keypoints of KL(target ‖ softmax(heatmap)) + ``dsnt_weight`` ×
    DSNT error (heatmap pixels).

    Parameters
    ----------
    heatmaps : Tensor, (B, K, H, W)
        Unnormalised heatmaps (``H == W``).
    keypoints : Tensor, (B, K, 2)
        Ground truth ``(u, v)`` in heatmap pixels.
    weights : Tensor, (B, K)
        1 for keypoints to learn, 0 to leave out.
    """
    B, K, H, W = heatmaps.shape
    target = heatmap_targets(keypoints, H, sigma).flatten(2)
    log_p = torch.log_softmax(heatmaps.flatten(2), -1)
    kl = (target * (torch.log(target.clamp_min(1e-30)) - log_p)).sum(-1)
    loss = kl
    if dsnt_weight:
        loss = loss + dsnt_weight * (dsnt_keypoints(heatmaps) - keypoints).norm(dim=-1)
    return (loss * weights).sum() / weights.sum().clamp_min(1.0)


def pck(pred, truth, weights, thresholds=(1, 2, 4)) -> dict:
    """Fraction of weighted keypoints whose error is ≤ each threshold (heatmap pixels),
    and the mean error. ``pred``, ``truth``: ``(N, K, 2)``; ``weights``: ``(N, K)``."""
    err = np.linalg.norm(np.asarray(pred, float) - np.asarray(truth, float), axis=-1)
    keep = np.asarray(weights) > 0
    out = {f"pck@{t}": float((err[keep] <= t).mean()) for t in thresholds}
    out["mean_error"] = float(err[keep].mean())
    return out


def predict(backbone: nn.Module, images: np.ndarray, batch_size: int = 64):
    """Argmax and DSNT keypoints ``(N, K, 2)`` (heatmap pixels) of preprocessed
    images ``(N, s, s, 3)`` in [0, 255]; the backbone runs in eval mode on its device."""
    backbone.eval()
    device = next(backbone.parameters()).device
    arg, dsnt = [], []
    with torch.no_grad():
        for i in range(0, len(images), batch_size):
            h = backbone(to_model_input(images[i : i + batch_size]).to(device)).float()
            arg.append(argmax_keypoints(h).cpu().numpy())
            dsnt.append(dsnt_keypoints(h).cpu().numpy())
    return np.concatenate(arg).astype(float), np.concatenate(dsnt).astype(float)


def train(
    data_dir,
    out,
    config: TrainConfig = TrainConfig(),
    *,
    init=None,
    device="cpu",
    progress: bool = True,
) -> dict:
    """Train (or resume) a backbone on ``data_dir`` and write the checkpoint ``out``.

    ``init``: the checkpoint whose weights start the run, required when ``config.init``
    is set (its :func:`weights_digest` must equal it). ``device`` (``'cpu'``, ``'cuda'``)
    changes where it runs, not the result's format.

    A checkpoint already at ``out`` with the same configuration is resumed (a finished
    one is returned as it is); one with another configuration is an error.

    Training stops with :class:`TrainingDiverged` (a ``ValueError``) at the first
    non-finite loss, or before saving non-finite weights; the checkpoint at ``out`` then
    stays the last good one (none is written if the first epoch diverges).

    Returns
    -------
    dict
        The checkpoint (``config``, ``history`` with per-epoch loss, validation PCK and
        time, ``model`` state, …).
    """
    out = Path(out)
    if out.exists() and out.is_dir():
        raise ValueError(f"out: expected a checkpoint file path, got the folder {out}")
    state = _resume(out, config)
    if state is not None and not _finite_state(state.get("model", {})):
        raise ValueError(
            f"out: {out} holds non-finite weights (a diverged run); delete it or choose "
            "another --out"
        )
    if state is not None and state["epoch"] >= config.epochs:
        return state
    size = BACKBONES[config.backbone].input_size
    train_set = load_keypoint_set(data_dir, "train", size, limit=config.images)
    val_set = load_keypoint_set(data_dir, "val", size)
    dataset = _describe(data_dir, train_set, val_set)
    torch.manual_seed(config.seed)  # the initial weights
    backbone = build_backbone(config.backbone, len(train_set.keypoint_names))
    if state is not None and state["dataset"] != dataset:
        raise ValueError(f"data: {data_dir} is not the dataset checkpoint {out} was trained on")
    lineage = _initial_weights(backbone, config, init) if state is None else None
    device = check_device(device)
    backbone = backbone.to(device, memory_format=torch.channels_last)
    optimiser = torch.optim.AdamW(
        backbone.parameters(), lr=config.lr, weight_decay=config.weight_decay
    )
    steps = -(-len(train_set) // config.batch_size)
    if config.schedule == "constant":
        scheduler = torch.optim.lr_scheduler.ConstantLR(optimiser, factor=1.0, total_iters=0)
    else:
        scheduler = torch.optim.lr_scheduler.OneCycleLR(
            optimiser, max_lr=config.lr, total_steps=config.epochs * steps, pct_start=0.15
        )
    if state is None:
        state = dict(format=FORMAT, config=asdict(config), dataset=dataset, epoch=0, history=[])
        if lineage is not None:
            state["lineage"] = lineage
    else:
        backbone.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
    augment = _augmentation(config).to(device)
    certify = _CertifiedTerm(config, backbone, train_set) if config.certified_weight else None
    stabilise = None
    if config.stability_weight:
        term = _StabilityTerm if config.stability_hulls == "photometric" else _BlockStabilityTerm
        stabilise = term(config, backbone)
    weights = torch.from_numpy((train_set.visibility > 0).astype(np.float32)).to(device)
    keypoints = torch.from_numpy(train_set.keypoints.astype(np.float32)).to(device)
    low_precision = config.precision == "bfloat16"
    for epoch in range(state["epoch"], config.epochs):
        start = time.perf_counter()
        torch.manual_seed(config.seed * 100_003 + epoch)
        order = torch.randperm(len(train_set))
        if certify is not None:
            certify.sampler.reseed(epoch)
        if stabilise is not None:
            stabilise.reseed(epoch)
        backbone.train()
        bound_total = stability_total = 0.0
        total, bar = (
            0.0,
            tqdm(range(steps), desc=f"epoch {epoch + 1}/{config.epochs}", disable=not progress),
        )
        for step in bar:
            idx = order[step * config.batch_size : (step + 1) * config.batch_size]
            x = augment(to_model_input(train_set.images[idx.numpy()]).to(device))
            x = x.contiguous(memory_format=torch.channels_last)
            idx = idx.to(device)
            with torch.autocast(device.type, torch.bfloat16, enabled=low_precision):
                heatmaps = backbone(x)
            loss = heatmap_loss(
                heatmaps.float(), keypoints[idx], weights[idx], config.sigma, config.dsnt_weight
            )
            if certify is not None and epoch >= config.certified_start:
                done = (epoch - config.certified_start + step / steps) / config.certified_ramp
                # Slow at first, while the bounds are loosest; at most ``certified_scale``.
                low, high = config.certified_scale_from, config.certified_scale
                scale = low + (high - low) * min(1.0, done) ** 2
                bound = certify(x, keypoints[idx], weights[idx], scale)
                bound_total += bound.item() * len(idx)
            else:
                bound = None
            terms = [(bound, config.certified_weight)]
            if stabilise is not None:
                unstable = stabilise(x)
                stability_total += unstable.item() * len(idx)
                terms.append((unstable, config.stability_weight))
            optimiser.zero_grad(set_to_none=True)
            _backward(loss, terms, list(backbone.parameters()))
            optimiser.step()
            scheduler.step()
            value = loss.item()
            if not math.isfinite(value):
                raise TrainingDiverged(_diverged(out, state["epoch"], epoch, step, value))
            total += value * len(idx)
            bar.set_postfix(loss=f"{value:.3f}")
        arg, dsnt = predict(backbone, val_set.images)
        vis = val_set.visibility > 0
        row = dict(
            epoch=epoch + 1,
            loss=total / len(train_set),
            seconds=time.perf_counter() - start,
            **({"bound_loss": bound_total / len(train_set)} if certify is not None else {}),
            **({"instability": stability_total / len(train_set)} if stabilise is not None else {}),
            **{f"val_{k}": v for k, v in pck(arg, val_set.keypoints, vis).items()},
            val_dsnt_mean_error=pck(dsnt, val_set.keypoints, vis)["mean_error"],
        )
        state.update(
            epoch=epoch + 1,
            history=state["history"] + [row],
            model={k: v.cpu() for k, v in backbone.state_dict().items()},
            optimizer=optimiser.state_dict(),
            scheduler=scheduler.state_dict(),
            keypoint_names=train_set.keypoint_names,
        )
        if not _finite_state(state["model"]):  # the last step's update overflowed
            raise TrainingDiverged(_diverged(out, epoch, epoch, steps - 1, "non-finite weights"))
        _save(out, state)
        if progress:
            print(json.dumps({k: round(v, 4) for k, v in row.items()}), flush=True)
    return state


def weights_digest(model: dict) -> str:
    """SHA-256 (hex) of a model state dict: every entry's name, dtype, shape and bytes, in
    name order. A checkpoint and its shipped copy (without optimiser state) share it."""
    digest = hashlib.sha256()
    for name in sorted(model):
        value = model[name].detach().cpu().contiguous()
        digest.update(f"{name}|{value.dtype}|{tuple(value.shape)}|".encode())
        digest.update(value.numpy().tobytes() if value.numel() else b"")
    return digest.hexdigest()


def _initial_weights(backbone: nn.Module, config: TrainConfig, init) -> list[dict] | None:
    """Load the weights of checkpoint ``init`` into ``backbone`` as ``config.init`` asks;
    returns the configurations of the stages that made them, earliest first (the initial
    checkpoint's ``lineage``, then its own; ``None`` without ``config.init``)."""
    if config.init is None:
        if init is not None:
            raise ValueError("init: given, but the configuration has no init digest (init=None)")
        return None
    if init is None:
        raise ValueError(
            f"init: expected the checkpoint whose weights have digest {config.init[:12]}…, got none"
        )
    _, state = load_checkpoint(init)
    if config_of(state).backbone != config.backbone:
        raise ValueError(
            f"init: expected a {config.backbone} checkpoint, got {config_of(state).backbone} "
            f"({init})"
        )
    if weights_digest(state["model"]) != config.init:
        raise ValueError(
            f"init: {init} holds weights with digest {weights_digest(state['model'])[:12]}…, "
            f"expected {config.init[:12]}…"
        )
    backbone.load_state_dict(state["model"])
    return [*state.get("lineage", []), asdict(config_of(state))]


def _diverged(out: Path, saved_epoch: int, epoch: int, step: int, what) -> str:
    """One line: where training diverged and which checkpoint is kept."""
    kept = (
        f"the checkpoint of epoch {saved_epoch} at {out} is kept"
        if saved_epoch
        else "no checkpoint was written"
    )
    what = f"the loss is {what}" if isinstance(what, float) else f"it produced {what}"
    return (
        f"lr: training diverged at epoch {epoch + 1}, step {step + 1}: {what} "
        f"(expected a smaller --lr); {kept}"
    )


def plot_history(checkpoints: dict):
    """Training curves of ``{name: checkpoint path}``: loss and validation PCK@1/2 px
    per epoch. Returns a matplotlib figure (two panels)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8), layout="constrained")
    loss, acc = fig.subplots(1, 2)
    for name, path in checkpoints.items():
        history = load_checkpoint(path)[1]["history"]
        epochs = [h["epoch"] for h in history]
        loss.plot(epochs, [h["loss"] for h in history], "o-", label=name)
        for key, style in (("val_pck@1", "o-"), ("val_pck@2", "s--")):
            acc.plot(epochs, [h[key] for h in history], style, label=f"{name} {key[4:]} px")
    loss.set(xlabel="epoch", ylabel="training loss", title="loss")
    acc.set(xlabel="epoch", ylabel="validation PCK", ylim=(0, 1), title="keypoints within r px")
    loss.legend()
    acc.legend(fontsize="small")
    return fig


def load_checkpoint(path) -> tuple[nn.Module, dict]:
    """The trained backbone (eval mode) and the checkpoint dictionary at ``path``; a
    ValueError naming it if it is not a checkpoint or holds non-finite weights."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint: no file at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file")
        config = config_of(state)
        backbone = build_backbone(config.backbone, len(state["keypoint_names"]))
        backbone.load_state_dict(state["model"])
    except Exception as exc:
        raise ValueError(f"checkpoint: cannot read {path} ({exc})") from exc
    if not _finite_state(state["model"]):
        raise ValueError(f"checkpoint: {path} holds non-finite weights (NaN or inf); retrain it")
    return backbone.eval(), state


def check_device(device) -> torch.device:
    """``torch.device(device)`` if torch can allocate on it (``'cpu'``, ``'cuda'``,
    ``'cuda:1'``, …), else a ValueError naming ``device``."""
    available = "cpu" + (", cuda" if torch.cuda.is_available() else "")
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device: expected a torch device ({available}), got {device!r}") from None
    try:
        torch.empty(0, device=parsed)
    except (RuntimeError, AssertionError) as exc:  # a CPU-only build raises AssertionError
        raise ValueError(
            f"device: expected an available torch device ({available}), got {device!r} ({exc})"
        ) from None
    return parsed


def config_of(state: dict) -> TrainConfig:
    """The :class:`TrainConfig` of checkpoint ``state``; one written before
    ``certified_method`` existed trained its bound term with forward bounds."""
    return TrainConfig(**{"certified_method": "forward", **state["config"]})


def _resume(out: Path, config: TrainConfig):
    if not out.exists():
        return None
    try:
        state = torch.load(out, map_location="cpu", weights_only=True)
        saved = config_of(state)
    except Exception as exc:
        raise ValueError(f"out: {out} exists and is not a readable checkpoint ({exc})") from exc
    differ = [
        f.name for f in fields(TrainConfig) if getattr(saved, f.name) != getattr(config, f.name)
    ]
    if differ:
        raise ValueError(
            f"out: {out} was trained with another configuration ({', '.join(differ)} differ); "
            "choose another --out or delete it"
        )
    return state


def _describe(data_dir, train_set: KeypointSet, val_set: KeypointSet) -> dict:
    from data_gen.dataset import load_coco

    return dict(
        path=str(Path(data_dir).resolve()),
        config=load_coco(data_dir)["info"].get("config"),
        train_images=len(train_set),
        val_images=len(val_set),
        input_size=train_set.input_size,
    )


def _save(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_bytes_atomic(path, buffer.getvalue())


def _backward(loss, terms, params: list) -> None:
    """Gradients of ``loss``, plus those of each ``(term, weight)`` of ``terms`` (a term
    may be None) rescaled to ``weight`` times the natural gradient's norm: each term pushes
    with a fixed share of the natural term's strength.

    Forward bounds of a trained network are loose by 10⁴–10⁶ even on tiny hulls, and the
    bound term's gradient was measured 10³–10⁶× the natural loss's (0.53) at hull scales
    10⁻⁴–10⁻² where its value is within 1–2·10⁴ of it; added with any fixed weight it
    swamps the natural gradient (validation PCK@2 0.98 → 0.1–0.4 within an epoch)."""
    terms = [(term, weight) for term, weight in terms if term is not None]
    if not terms:
        loss.backward()
        return
    retain = dict(retain_graph=True, allow_unused=True)
    natural = torch.autograd.grad(loss, params, **retain)
    norm = lambda gs: torch.sqrt(sum((g**2).sum() for g in gs if g is not None))  # noqa: E731
    total = list(natural)
    for term, weight in terms:
        grads = torch.autograd.grad(term, params, **retain)
        factor = weight * norm(natural) / norm(grads).clamp_min(1e-30)
        if not torch.isfinite(factor):
            factor = torch.zeros(())
        for i, c in enumerate(grads):
            if c is not None:
                total[i] = c * factor if total[i] is None else total[i] + factor * c
    for p, g in zip(params, total):
        p.grad = g


class _CertifiedTerm:
    """The bound term of one training run: a hull sampler and the backbone's
    differentiable graph (:mod:`kpstudy.models.certified`), its batch norms normalising by the
    statistics of each batch's natural pass (:class:`kpstudy.models.certified.BatchStatistics`)."""

    def __init__(self, config: TrainConfig, backbone: nn.Module, train_set: KeypointSet):
        from kpstudy.models.certified import (
            BatchStatistics,
            HullSampler,
            bound_graph,
            occluder_patches,
        )

        W, H = train_set.image_size
        s = train_set.input_size
        self.hulls, self.sigma = config.certified_hulls, config.sigma
        self.method = config.certified_method
        self.sampler = HullSampler(occluder_patches(seed=config.seed), (s / W, s / H), config.seed)
        self.backbone = backbone
        self.graph = bound_graph(backbone)
        self.statistics = BatchStatistics(backbone)

    def __call__(self, x, keypoints, weights, scale: float) -> torch.Tensor:
        """The term on the first hulls of batch ``x``, after its natural pass."""
        from kpstudy.models.certified import hull_bounds, robust_heatmap_loss

        n = min(self.hulls, len(x))
        vertices = self.sampler(x[:n].contiguous())
        with self.statistics.frozen():
            lower, upper = hull_bounds(self.graph, vertices, scale, self.method)
        return robust_heatmap_loss(lower, upper, keypoints[:n], weights[:n], self.sigma)


class _StabilityTerm:
    """The first layer's ReLU instability over a random brightness or contrast hull
    around every image of a batch (:func:`kpstudy.models.certified.relu_instability`):
    the layer's pre-activations at the image are the natural pass's (a forward hook on
    its batch norm), their changes at the hull's other vertices the convolution of the
    image differences scaled by the batch norm with the batch's statistics."""

    def __init__(self, config: TrainConfig, backbone: nn.Module):
        first = list(backbone.children())[:2]
        if not (
            len(first) == 2
            and isinstance(first[0], nn.Conv2d)
            and isinstance(first[1], nn.BatchNorm2d)
        ):
            raise ValueError(
                f"stability_weight: expected a backbone that starts with a convolution and a "
                f"batch norm, got {config.backbone!r}"
            )
        self.conv, self.norm = first
        self.seed = config.seed
        self.norm.register_forward_hook(self._record)
        self.reseed(0)

    def reseed(self, epoch: int) -> None:
        """Draw from the stream of ``epoch`` (a resumed run draws the same hulls)."""
        self.rng = np.random.default_rng([self.seed, 13, epoch])

    def _record(self, m, inputs, output) -> None:
        if m.training:
            self.centre = output
            self.var = inputs[0].detach().float().var((0, 2, 3), unbiased=False)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """The term on batch ``x (B, 3, s, s)`` in [0, 1], after its natural pass."""
        from kpstudy.models.certified import PHOTOMETRIC, photometric_pair, relu_instability

        images = x.detach().float().cpu().numpy()
        kinds = self.rng.integers(len(PHOTOMETRIC), size=len(images))
        pairs = np.stack(
            [photometric_pair(im, PHOTOMETRIC[k], self.rng) for im, k in zip(images, kinds)]
        )
        diff = torch.from_numpy(pairs).to(x.device) - x.detach().float()[:, None]
        conv = self.conv
        moved = nn.functional.conv2d(
            diff.flatten(0, 1), conv.weight, None, conv.stride, conv.padding, conv.dilation
        )
        gain = self.norm.weight / torch.sqrt(self.var + self.norm.eps)
        deltas = (moved * gain[:, None, None]).unflatten(0, (len(x), 2))
        return relu_instability(self.centre.float(), deltas)


class _BlockStabilityTerm:
    """Every ReLU's instability over random block hulls around the first
    :data:`BLOCK_STABILITY_HULLS` images of a batch (module docstring): each ReLU's input
    (a forward hook) at the hull's points, :func:`kpstudy.models.certified.relu_instability`
    of its sampled band, averaged over the ReLUs. The points pass in the backbone's mode
    (training: its batch norms normalise by their own statistics) and precision."""

    def __init__(self, config: TrainConfig, backbone: nn.Module):
        relus = [m for m in backbone.modules() if isinstance(m, nn.ReLU)]
        if not relus:
            raise ValueError(
                "stability_hulls: 'blocks' expected a backbone with nn.ReLU modules, "
                f"got {config.backbone!r}"
            )
        for relu in relus:
            relu.register_forward_hook(self._record)
        self.backbone, self.seed = backbone, config.seed
        self.low_precision = config.precision == "bfloat16"
        self.inputs: list | None = None
        self.reseed(0)

    def reseed(self, epoch: int) -> None:
        """Draw from the stream of ``epoch`` (a resumed run draws the same hulls)."""
        self.rng = np.random.default_rng([self.seed, 17, epoch])

    def _record(self, m, inputs, output) -> None:
        if self.inputs is not None:
            self.inputs.append(inputs[0])

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """The term on batch ``x (B, 3, s, s)`` in [0, 1]."""
        from kpstudy.models.certified import block_hull_points, relu_instability

        points = block_hull_points(x[:BLOCK_STABILITY_HULLS], self.rng)
        B, P = points.shape[:2]
        self.inputs = []
        try:
            flat = points.flatten(0, 1).contiguous(memory_format=torch.channels_last)
            with torch.autocast(x.device.type, torch.bfloat16, enabled=self.low_precision):
                self.backbone(flat)
            inputs = self.inputs
        finally:
            self.inputs = None
        terms = []
        for a in inputs:
            a = a.unflatten(0, (B, P))
            # The band's ends are sampled values: take them before casting up (memory).
            low, high = a.amin(1).float(), a.amax(1).float()
            centre = a[:, 0].float()
            terms.append(relu_instability(centre, torch.stack([low, high], 1) - centre[:, None]))
        return torch.stack(terms).mean()


def _augmentation(config: TrainConfig) -> nn.Module:
    steps: list[nn.Module] = []
    if config.jitter:
        j = config.jitter
        steps.append(KA.ColorJiggle(j, j, j, 0.0, p=1.0))
    if config.noise:
        steps.append(KA.RandomGaussianNoise(std=config.noise, p=1.0))
    return nn.Sequential(*steps)
