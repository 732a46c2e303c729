"""`python -m kpstudy reproduce`: the whole study at a chosen scale, results under results/.

Stages, in order; each is skipped when its outputs are current:

1. **data** (paper §8.1): the rendered COCO dataset (data_gen), the perturbation sets of
   its test seed images (objects at the render's resolution, blocks at the ResNet-18
   input, brightness and contrast at the CNN input). Reused when its settings match.
2. **train**: the CNN and the ResNet-18 (:data:`RESNET`) heatmap backbones
   (:func:`kpstudy.models.training.train`, which resumes an interrupted run and returns a
   finished one as it is), and the verification-friendly CNN (:data:`FRIENDLY`: the
   patch-decoder CNN trained with the bound term of :mod:`kpstudy.models.certified`). A
   model whose quick-profile checkpoint ships with kpstudy (:data:`SHIPPED`, written by
   :func:`ship`) gets a copy of it when it was made by the same recipe on the same
   dataset; otherwise, or when ``retrain`` names the model, it is trained.
3. **notebooks**: ``notebooks/NN_*.ipynb`` run by papermill with the profile's
   parameters into ``results/<profile>/notebooks/``. Each writes its tables (CSV and
   Markdown, the paper's numbers beside ours) under ``tables/`` and its figures under
   ``figures/``. A notebook reruns only when its parameters or its inputs changed; the
   verification campaigns inside (06–08) resume from their SQLite stores.
4. **report**: ``REPORT.md``, every table and figure with a short reading of the trends
   (:mod:`kpstudy.study.report`).

The ``quick`` profile runs everything at reduced counts on 2 CPU cores (a smoke test: 3
seeds a cell); ``standard`` runs the tables at the study's scale on 2 cores (50 seeds a
table, every method under a node budget per instance or hull);
``paper`` has the paper's counts (200 seeds, 3000 images × 5000 Monte Carlo samples) and
is meant for a GPU (training) and a Dask cluster (``--scheduler``, the campaigns).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from kpstudy import _checks
from kpstudy.io import source_fingerprint, write_bytes_atomic, write_text_atomic
from kpstudy.study.reference import log_stage

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
#: The stages of :func:`reproduce`, in the order they run.
STAGES = ("data", "train", "notebooks", "report")
#: The verification-friendly CNN's backbone (:mod:`kpstudy.models.cnn`), also its name in
#: the study's tables and under ``models/``.
FRIENDLY_MODEL = "cnn_patch_smooth"
#: The verification-friendly CNN's recipe, first stage (``TrainConfig`` fields beside the
#: profile's seed): natural epochs, then a forward-bound term over sub-hulls that grow to
#: 5 % of the hulls' size.
FRIENDLY = dict(
    backbone=FRIENDLY_MODEL,
    epochs=20,
    certified_weight=2.0,
    certified_scale=0.05,
    certified_start=8,
    certified_ramp=4,
    certified_method="forward",
)
#: Its second stage, from the first stage's weights: the verifier's own zonotope over
#: one sub-hull per batch growing from 10 % to 50 % of the hulls' size, the learning rate
#: rising to 3e-4 and annealing (a constant rate cost PCK@2 0.03).
FRIENDLY_FINETUNE = dict(
    backbone=FRIENDLY_MODEL,
    epochs=2,
    lr=3e-4,
    schedule="onecycle",
    certified_weight=2.0,
    certified_hulls=1,
    certified_start=0,
    certified_ramp=2,
    certified_scale_from=0.1,
    certified_scale=0.5,
    certified_method="zonotope",
)
#: The verification-friendly CNN's stages in order, each from the weights of the one before.
FRIENDLY_STAGES = (FRIENDLY, FRIENDLY_FINETUNE)
#: The ResNet-18's recipe (``TrainConfig`` fields), the paper's on 2 CPU cores: 30 epochs of
#: batches of 32 images, targets of σ = 2 heatmap pixels, a one-cycle learning rate peaking
#: at 2e-3, bfloat16 forward passes. The profile's ``seed``, ``resnet_epochs``,
#: ``resnet_images`` and ``precision`` take the place of its own (:func:`resnet_recipe`).
RESNET = dict(
    backbone="resnet18", epochs=30, batch_size=32, sigma=2.0, lr=2e-3, precision="bfloat16"
)
_WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "weights"
#: The checkpoints that ship with kpstudy, by model, each trained on the quick profile's
#: dataset and written by :func:`ship` beside its card: the verification-friendly CNN by
#: :data:`FRIENDLY_STAGES`, the ResNet-18 by :data:`RESNET` on every training image (where
#: the file is missing, the model is trained).
SHIPPED = {
    FRIENDLY_MODEL: _WEIGHTS / f"{FRIENDLY_MODEL}_quick.pt",
    "resnet18": _WEIGHTS / "resnet18_quick.pt",
}


@dataclass(frozen=True)
class Profile:
    """Every count of one run of the study.

    Attributes
    ----------
    dataset_images, dataset_size : rendered images and their ``'WxH'`` size.
    perturbed_seeds : test images that get perturbation sets (the campaigns' seeds).
    cnn_epochs, resnet_epochs, cnn_images, resnet_images : training length and the most
        training images used (``None``: all).
    images, samples : T-prob's overhead views and Monte Carlo samples per view.
    seeds : seed images per campaign (≤ ``perturbed_seeds``); ``resnet_seeds`` for T-resnet.
    timeout, resnet_timeout : verification seconds per instance (with ``nodes``, a cap).
    method, nodes : the allocation method's bounds (``'auto'``: the zonotope) and node
        budget per instance (``None``: the seconds decide): the same verdicts on any
        machine.
    allocation : per model (``'cnn'``, :data:`FRIENDLY_MODEL`) of T-local and T-global, the
        allocation method's ``method``, ``nodes`` and ``timeout`` in place of the profile's
        (:func:`kpstudy.study.campaign.run_study`'s ``allocation``).
    tolerance_units : the readings of the allocated tolerances every campaign and T-prob
        run under (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`), the first also with the
        pose-bound method.
    local_pose_bound, global_pose_bound : per model (``'cnn'``, :data:`FRIENDLY_MODEL`), the
        pose-bound method's :class:`kpstudy.study.campaign.Settings` fields in T-local and
        T-global (beside the allocation method): ``pose_bound_method``,
        ``pose_bound_timeout`` (seconds per hull), ``pose_bound_nodes`` (a node budget per
        hull: the same verdicts on any machine), ``pose_bound_start_depth``,
        ``pose_bound_start_splits``. A model left out skips the method. ``'zonotope'`` is
        far tighter on the CNN than ``'forward'`` but takes seconds to minutes per node on
        2 CPU cores.
    resnet_pose_bound : the same for ``'resnet18'`` in T-resnet.
    precision : the natural CNN's and ResNet-18's training forward pass
        (:class:`kpstudy.models.training.TrainConfig`'s ``precision``, in place of
        :data:`RESNET`'s; the verification-friendly CNN's recipe keeps its own).
    symmetry_backbone : the model of F-sym (``'resnet18'``, as in the paper, or ``'cnn'``).
    figure_images : seed images of F-sym and F-alloc.
    overlapping_share : the share of each seed's object occlusions whose patch is aimed at
        the airplane (:func:`data_gen.perturb.make_perturbations`; ``None``: every patch at
        a uniformly random place, about one in ten overlapping), so that the overlapping
        cells of T-local get enough seeds.
    workers : local processes per campaign, each with ``cpu_count // workers`` threads
        (quick: one, so that every hull has both cores and the tables' per-hull times
        are 2-core times).
    """

    name: str
    dataset_images: int
    dataset_size: str
    perturbed_seeds: int
    cnn_epochs: int
    resnet_epochs: int
    images: int
    samples: int
    seeds: int
    resnet_seeds: int
    timeout: float
    resnet_timeout: float
    cnn_images: int | None = None
    resnet_images: int | None = None
    method: str = "auto"
    nodes: int | None = None
    allocation: dict = field(default_factory=dict)
    tolerance_units: tuple = ("heatmap", "paper")
    local_pose_bound: dict = field(default_factory=lambda: dict(LOCAL_POSE_BOUND))
    global_pose_bound: dict = field(default_factory=lambda: dict(GLOBAL_POSE_BOUND))
    resnet_pose_bound: dict = field(default_factory=lambda: dict(RESNET_POSE_BOUND))
    precision: str = "float32"
    symmetry_backbone: str = "resnet18"
    figure_images: int = 50
    workers: int = 1
    seed: int = 0
    overlapping_share: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("str", "dict", "tuple") or f.name == "seed" or value is None:
                continue
            if f.name == "overlapping_share":
                if isinstance(value, bool) or not 0 <= value <= 1:
                    raise ValueError(f"overlapping_share: expected None or [0, 1], got {value!r}")
                continue
            if isinstance(value, bool) or not value > 0:
                raise ValueError(f"{f.name}: expected a positive number, got {value!r}")
        if self.seeds > self.perturbed_seeds or self.resnet_seeds > self.perturbed_seeds:
            raise ValueError(
                f"seeds: expected at most perturbed_seeds={self.perturbed_seeds} seed images, "
                f"got seeds={self.seeds}, resnet_seeds={self.resnet_seeds}"
            )
        from kpstudy.pose.allocation import TOLERANCE_UNITS

        readings = self.tolerance_units
        if (
            not isinstance(readings, tuple)
            or not readings
            or len(set(readings)) != len(readings)
            or not set(readings) <= set(TOLERANCE_UNITS)
        ):
            raise ValueError(
                f"tolerance_units: expected a tuple of distinct readings from "
                f"{TOLERANCE_UNITS}, got {readings!r}"
            )
        from kpstudy.certify.hull import pose_bound_options
        from kpstudy.study.campaign import ALLOCATION_SETTINGS, allocation_options

        budgets = [("", dict(method=self.method, nodes=self.nodes))]
        for model, chosen in self.allocation.items():
            if (
                model not in ("cnn", FRIENDLY_MODEL)
                or not isinstance(chosen, dict)
                or not set(chosen) <= set(ALLOCATION_SETTINGS)
            ):
                raise ValueError(
                    f"allocation: expected {{'cnn' or {FRIENDLY_MODEL!r}: {{setting: value}}}} "
                    f"with settings from {tuple(ALLOCATION_SETTINGS)}, got {model!r}: {chosen!r}"
                )
            budgets.append(("allocation: ", chosen))
        for where, chosen in budgets:
            allocation_options(where, **chosen)
        for name, models in (
            ("local_pose_bound", ("cnn", FRIENDLY_MODEL)),
            ("global_pose_bound", ("cnn", FRIENDLY_MODEL)),
            ("resnet_pose_bound", ("resnet18",)),
        ):
            for model, chosen in getattr(self, name).items():
                if model not in models or not isinstance(chosen, dict):
                    raise ValueError(
                        f"{name}: expected {{{' or '.join(map(repr, models))}: "
                        f"{{setting: value}}}}, got {model!r}: {chosen!r}"
                    )
                pose_bound_options(f"{name}: ", **chosen)
        if self.symmetry_backbone not in ("cnn", "resnet18"):
            raise ValueError(
                f"symmetry_backbone: expected 'cnn' or 'resnet18', got {self.symmetry_backbone!r}"
            )


#: The quick profile's pose-bound method in T-local per model: the paper's CNN with
#: forward bounds on the root (its zonotope proves most m = 2 hulls, but in minutes each,
#: and leaves some open after 16 nodes),
#: the verification-friendly CNN with the zonotope from the hull split ⌈1.75 m⌉ times (4, 6
#: and 7 splits at m = 2, 3, 4: nodes of about a third of the hull per direction, where
#: its hardest hulls close; a shallower start bounds the same number of deeper nodes after
#: larger, costlier and undecisive ones), up to 768 nodes and then 64 aimed at the cells
#: that keep an `unknown` open (the hardest quick hull takes about 610 nodes from any start
#: depth from 6 to 8, every other one 280 or fewer). Node budgets give
#: the same verdicts on any machine; the seconds only cap a slow one.
LOCAL_POSE_BOUND = {
    "cnn": dict(pose_bound_method="forward", pose_bound_timeout=60.0, pose_bound_nodes=1),
    FRIENDLY_MODEL: dict(
        pose_bound_method="zonotope",
        pose_bound_timeout=600.0,
        pose_bound_nodes=768,
        pose_bound_start_splits=1.75,
        pose_bound_refine_nodes=64,
    ),
}
#: The same in T-global: the zonotope for both, up to 3 nodes per hull (every hull the
#: quick grid decides needs at most 3; a 4th only cost the three hulls it leaves
#: `unknown` another ~28 s each, and fewer nodes give supersets of the regions, so the
#: same verdicts). The 300 s cap leaves the node budget to decide on a loaded machine too
#: (at 120 s the cap ended 4 to 12 hulls' searches).
GLOBAL_POSE_BOUND = {
    model: dict(pose_bound_method="zonotope", pose_bound_timeout=300.0, pose_bound_nodes=3)
    for model in ("cnn", FRIENDLY_MODEL)
}
#: The pose-bound method in T-resnet: the zonotope on no node, i.e. the argmax → PnP pose
#: at the seed, the hull's corners and random and targeted images (a pose outside Ξ is a
#: counterexample) and no bounds. At 256 × 256 a zonotope node of ResNet-18 takes 7–100 s
#: on one core, and on a block hull of two images it decides nodes only from about 14
#: splits down (every pixel stays possible at 10), ~10⁴ nodes a hull; on the study's
#: hulls of four images from about 28, ~10⁸. No node budget within reach decides one.
RESNET_POSE_BOUND = {
    "resnet18": dict(pose_bound_method="zonotope", pose_bound_timeout=600.0, pose_bound_nodes=0)
}

#: The standard profile's pose-bound method in T-local: the friendly CNN as in the quick
#: profile; the natural CNN with the zonotope too (forward bounds decide none of its
#: object hulls), from the same start depth, on 2 nodes: on 18 standard hulls (3 seeds)
#: 8 nodes decided the same 34 of 72 cells as the root (violated, at 0 nodes) and cost the
#: 38 others a median 8.7 s and up to 62 s a hull.
STANDARD_LOCAL_POSE_BOUND = {
    "cnn": dict(
        pose_bound_method="zonotope",
        pose_bound_timeout=600.0,
        pose_bound_nodes=2,
        pose_bound_start_splits=1.75,
    ),
    FRIENDLY_MODEL: dict(LOCAL_POSE_BOUND[FRIENDLY_MODEL]),
}
#: The standard profile's allocation method per model in T-local and T-global: the
#: profile's zonotope on 2 nodes for the friendly CNN; forward bounds on the natural CNN,
#: whose zonotope root bound is ~10⁶ below zero under the 'paper' reading (16 nodes: 110 s
#: an instance, none decided). The allocation method bounds each (α, κ)
#: cell of a hull on its own, about 1.3 s a zonotope node on 2 cores: 16 nodes on the
#: 2200 'paper' instances would take ~5 hours.
STANDARD_ALLOCATION = {"cnn": dict(method="forward")}

#: The quick profile. Its campaigns run in two one-thread workers: on a machine shared with
#: other jobs, a search on two torch threads waits at every operator for the thread the
#: scheduler took away (beside the test suite, a quick object hull's node took 2.5 s on two
#: threads and 0.93 s on one), while one-thread workers slow down only by their share of
#: the cores. The allocation method's 2 nodes take about a second an instance; its 60 s cap
#: leaves them to the node budget on a loaded machine too (a 10 s cap fired on 48 of them
#: beside the suite).
_QUICK = Profile(
    "quick",
    dataset_images=2000,
    dataset_size="640x400",
    perturbed_seeds=8,
    cnn_epochs=16,
    resnet_epochs=30,
    images=30,
    samples=1000,
    seeds=3,
    resnet_seeds=8,
    timeout=60.0,
    resnet_timeout=20.0,
    method="forward",
    nodes=2,
    workers=2,
    precision="bfloat16",
)

#: The named profiles (:func:`profile`): ``quick``, ``standard`` and ``paper``.
PROFILES = {
    "quick": _QUICK,
    # The study's scale on 2 cores: the quick profile's dataset and models, 60 test seed
    # images with perturbation sets (50 per table), every method under a node budget per
    # instance or hull, T-prob at 200 views × 5000 samples (1000 views took over an hour);
    # the quick profile's two one-thread workers (a hull on one thread takes 1.1-1.8x its
    # 2-thread time: more hulls an hour, and the tables' times are one-core times).
    "standard": replace(
        _QUICK,
        name="standard",
        perturbed_seeds=60,
        images=200,
        samples=5000,
        seeds=50,
        resnet_seeds=50,
        timeout=600.0,
        resnet_timeout=600.0,
        method="auto",
        nodes=2,
        allocation=STANDARD_ALLOCATION,
        local_pose_bound=STANDARD_LOCAL_POSE_BOUND,
        overlapping_share=0.5,
    ),
    "paper": Profile(
        "paper",
        dataset_images=7000,
        dataset_size="1920x1200",
        perturbed_seeds=200,
        cnn_epochs=20,
        resnet_epochs=30,
        images=3000,
        samples=5000,
        seeds=200,
        resnet_seeds=200,
        timeout=600.0,
        resnet_timeout=3600.0,
        local_pose_bound={
            model: dict(pose_bound_method="zonotope", pose_bound_timeout=600.0)
            for model in ("cnn", FRIENDLY_MODEL)
        },
        global_pose_bound={
            model: dict(pose_bound_method="zonotope", pose_bound_timeout=600.0)
            for model in ("cnn", FRIENDLY_MODEL)
        },
        resnet_pose_bound={
            "resnet18": dict(pose_bound_method="zonotope", pose_bound_timeout=3600.0)
        },
        figure_images=3000,
    ),
}


def profile(name: str, **overrides) -> Profile:
    """The named profile with some fields replaced (e.g. ``images=10``)."""
    _checks.choice(name, "profile", sorted(PROFILES))
    known = {f.name for f in fields(Profile)} - {"name"}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"overrides: unknown profile fields {unknown}; expected {sorted(known)}")
    return replace(PROFILES[name], **{k: v for k, v in overrides.items() if v is not None})


def reproduce(
    prof: str | Profile,
    out_root="results",
    *,
    stages=STAGES,
    notebooks=None,
    scheduler: str | None = None,
    progress: bool = True,
    retrain=(),
    command: str | None = None,
) -> Path:
    """Run ``stages`` of the profile and return its results folder ``out_root/<name>``
    (``notebooks``: names of the notebooks stage's notebooks to run, e.g. ``['06_local']``,
    default all; ``retrain``: models of :data:`SHIPPED` to train even where the shipped
    checkpoint fits, :func:`train_models`). Each stage, finished or interrupted, adds its
    seconds, the commit and ``command`` (the command line, where there is one) to the
    folder's ``runs.jsonl`` (:func:`kpstudy.study.reference.log_stage`). When the
    notebooks or the report ran and a campaign's records there hold instances that ended
    ``'error'``, every stage still runs; then they are printed and
    :class:`kpstudy.study.campaign.InstanceErrors` is raised with their count
    (:func:`campaign_errors`)."""
    prof = profile(prof) if isinstance(prof, str) else prof
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise ValueError(f"stages: expected some of {STAGES}, got {unknown}")
    names = sorted(p.stem for p in NOTEBOOKS.glob("[0-9]*.ipynb"))
    unknown = [n for n in notebooks or () if n not in names]
    if unknown:
        raise ValueError(f"notebooks: expected some of {names}, got {unknown}")
    _check_retrain(retrain)
    out = Path(out_root) / prof.name
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    for stage in STAGES:
        if stage not in stages:
            continue
        start, finished = time.perf_counter(), False
        try:
            if stage == "data":
                data(prof, out, progress=progress)
            elif stage == "train":
                train_models(prof, out, progress=progress, retrain=retrain)
            elif stage == "notebooks":
                run_notebooks(prof, out, scheduler=scheduler, progress=progress, only=notebooks)
            else:
                from kpstudy.study.report import write_report

                write_report(out, asdict(prof))
            finished = True
        finally:
            seconds = time.perf_counter() - start
            log_stage(out, stage, seconds, finished=finished, command=command)
        timings[stage] = round(seconds, 1)
        print(f"[reproduce] {stage}: {timings[stage]} s", flush=True)
    if {"notebooks", "report"} & set(stages):
        campaign_errors(out)
    return out


def campaign_errors(out: Path) -> None:
    """Print the campaign instances of the tables' records under ``out/tables`` that
    ended ``'error'``, a line each, and raise :class:`kpstudy.study.campaign.InstanceErrors`
    with their count; nothing when there are none (the instances as the REPORT lists
    them: :func:`kpstudy.study.report.error_instances`)."""
    from kpstudy.study.campaign import InstanceErrors
    from kpstudy.study.report import error_instances

    errors, total, files = [], 0, []
    for name, (count, failed) in error_instances(out).items():
        total += count
        if failed:
            files.append(str(Path(out) / "tables" / f"{name}_records.csv"))
        errors += [f"[reproduce] error: {name} {label}: {text}" for label, text in failed]
    if errors:
        print("\n".join(errors), flush=True)
        raise InstanceErrors(
            f"{len(errors)} of {total} campaign instances ended 'error' (listed above; their "
            f"records: {', '.join(files)}); the results in {out} are incomplete"
        )


def is_timing(column: str) -> bool:
    """Whether a table column measures time (``time``, ``pb_time_mean``, ``seconds`` …)
    or memory (``peak_memory_mib``): the things two runs of a profile may differ in."""
    return any(word in column for word in ("time", "seconds", "memory"))


def compare_results(a, b) -> dict[str, str]:
    """What differs between two results folders of a profile (``results/<profile>``).

    Compares every table (``tables/*.csv``) cell by cell, its timing columns
    (:func:`is_timing`) aside, and every checkpoint's weights (``models/*.pt``): a
    verdict that hangs on a time cap shows as a differing ``status``, ``stopped`` or
    ``capped`` cell. Returns ``{path relative to the folder: 'same' or what differs}``
    over the files of either folder; what differs in a verification table or its records
    then names, apart, the cells where a time cap rather than the node budget ended a
    search in either run (:func:`kpstudy.study.comparison.time_caps`).

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     for run, seconds in (("a", 1.5), ("b", 9.0)):
    ...         Path(tmp, run, "tables").mkdir(parents=True)
    ...         _ = Path(tmp, run, "tables", "t.csv").write_text(f"status,time\\nholds,{seconds}")
    ...     compare_results(Path(tmp, "a"), Path(tmp, "b"))
    {'tables/t.csv': 'same'}
    """
    import pandas as pd

    from kpstudy.models.training import load_checkpoint, weights_digest
    from kpstudy.study.comparison import time_caps

    roots = []
    for name, root in (("a", a), ("b", b)):
        root = Path(root)
        if not (root / "tables").is_dir():
            raise ValueError(f"{name}: expected a results folder with tables/, got {str(root)!r}")
        roots.append(root)
    files = sorted(
        {
            p.relative_to(root).as_posix()
            for root in roots
            for p in [*root.glob("tables/*.csv"), *root.glob("models/*.pt")]
        }
    )
    out = {}
    for rel in files:
        pa, pb = (root / rel for root in roots)
        if not (pa.is_file() and pb.is_file()):
            out[rel] = f"only in {'a' if pa.is_file() else 'b'}"
        elif rel.endswith(".pt"):
            da, db = (weights_digest(load_checkpoint(p)[1]["model"]) for p in (pa, pb))
            out[rel] = "same" if da == db else "weights differ"
        else:
            read = (pd.read_csv(pa), pd.read_csv(pb))
            ta, tb = read
            if list(ta.columns) != list(tb.columns) or len(ta) != len(tb):
                out[rel] = f"shape differs: {ta.shape} against {tb.shape}" + time_caps(*read)
                continue
            cols = [c for c in ta.columns if not is_timing(c)]
            ta, tb = (t[cols].astype(object).where(t[cols].notna(), "") for t in (ta, tb))
            unequal = ta.astype(str) != tb.astype(str)
            differs = unequal.sum()
            differs = differs[differs > 0]
            out[rel] = (
                "same"
                if differs.empty
                else "cells differ: "
                + ", ".join(f"{c} ({n})" for c, n in differs.items())
                + time_caps(*read, unequal.any(axis=1).to_numpy())
            )
    return out


def data(prof: Profile, out: Path, *, progress: bool = True) -> Path:
    """The dataset and its perturbation sets under ``out/data``."""
    from data_gen.dataset import generate_dataset, load_coco
    from data_gen.perturb import KINDS, make_perturbations
    from kpstudy.models import BACKBONES

    folder = out / "data"
    wanted = {"n": prof.dataset_images, "size": prof.dataset_size, "seed": prof.seed}
    try:
        config = load_coco(folder)["info"]["config"]
        size = "x".join(map(str, config["size"]))
        have = {"n": config["n"], "size": size, "seed": config["seed"]}
    except FileNotFoundError:
        have = None
    fresh = have != wanted
    if fresh:
        generate_dataset(
            folder,
            prof.dataset_images,
            prof.dataset_size,
            prof.seed,
            workers=min(2, os.cpu_count() or 1),
            overwrite=True,
            progress=progress,
        )
    sizes = {"blocks": BACKBONES["resnet18"].input_size}
    for kind in KINDS:
        size = sizes.get(kind, BACKBONES["cnn"].input_size)
        meta = folder / "perturbations" / kind / "meta.json"
        config = json.loads(meta.read_text())["config"] if meta.is_file() else None
        share = {"overlapping_share": prof.overlapping_share} if kind == "objects" else {}
        if (
            fresh
            or config is None
            or config["input_size"] != [size, size]
            or len(config["ids"]) != prof.perturbed_seeds
            or config.get("overlapping_share") != share.get("overlapping_share")
        ):
            make_perturbations(
                folder,
                kind,
                seeds=prof.perturbed_seeds,
                seed=prof.seed,
                input_size=size,
                overwrite=True,
                **share,
            )
    return folder


def checkpoints(out: Path) -> dict[str, Path]:
    """Where the train stage writes each backbone's checkpoint."""
    names = ("cnn", FRIENDLY_MODEL, "resnet18")
    return {name: Path(out) / "models" / f"{name}.pt" for name in names}


def friendly_recipe(prof: Profile) -> tuple:
    """The verification-friendly CNN's :class:`kpstudy.models.training.TrainConfig` stages
    (:data:`FRIENDLY_STAGES`) on ``prof``; each ``init`` after the first is left ``None``
    (the weights of the stage before fill it)."""
    from kpstudy.models.training import TrainConfig

    common = dict(images=prof.cnn_images, seed=prof.seed)
    return tuple(TrainConfig(**stage, **common) for stage in FRIENDLY_STAGES)


def follows_recipe(state: dict, stages) -> bool:
    """Whether checkpoint ``state`` is the last of ``stages`` (``TrainConfig``s), begun
    from weights the stages before made in order (its ``lineage``); the ``init`` digests,
    which name weights trained on some machine, are not compared."""
    from kpstudy.models.training import config_of

    def unseeded(config):
        return replace(config_of({"config": config}), init=None)

    made = [*state.get("lineage", []), state["config"]]
    return [unseeded(c) for c in made] == [replace(c, init=None) for c in stages]


def resnet_recipe(prof: Profile):
    """The ResNet-18's :class:`kpstudy.models.training.TrainConfig` on ``prof``:
    :data:`RESNET` with the profile's seed, epochs, training images and precision."""
    from kpstudy.models.training import TrainConfig

    return TrainConfig(
        **{
            **RESNET,
            "epochs": prof.resnet_epochs,
            "images": prof.resnet_images,
            "seed": prof.seed,
            "precision": prof.precision,
        }
    )


def _check_retrain(retrain) -> None:
    """A ValueError unless ``retrain`` is a collection of :data:`SHIPPED`'s model names."""
    if isinstance(retrain, str) or not set(retrain) <= set(SHIPPED):
        raise ValueError(f"retrain: expected some of {', '.join(SHIPPED)}, got {retrain!r}")


def train_models(prof: Profile, out: Path, *, progress: bool = True, retrain=()) -> dict[str, Path]:
    """Train (or resume, or reuse) the CNN, the verification-friendly CNN and the
    ResNet-18 on ``out/data``.

    A model of :data:`SHIPPED` whose shipped checkpoint was made by the same recipe on the
    same dataset gets a copy of it, unless ``retrain`` (model names) names it: then a copy
    made earlier (a checkpoint without optimiser state) is deleted and the model trained;
    a checkpoint trained here, finished or not, stays and is resumed."""
    import torch

    from data_gen.dataset import load_coco
    from kpstudy.models.training import TrainConfig, config_of, train, weights_digest

    _check_retrain(retrain)
    paths = checkpoints(out)
    dataset = load_coco(out / "data")["info"]["config"]
    stages = friendly_recipe(prof)
    configs = {
        "cnn": TrainConfig(
            "cnn",
            epochs=prof.cnn_epochs,
            images=prof.cnn_images,
            seed=prof.seed,
            precision=prof.precision,
        ),
        "resnet18": resnet_recipe(prof),
    }
    device = "cuda" if torch.cuda.is_available() else "cpu"

    def load(file: Path) -> dict:
        return torch.load(file, map_location="cpu", weights_only=True)

    def made_by(file: Path, config: TrainConfig) -> bool:
        state = load(file)
        return config_of(state) == config and state["dataset"]["config"] == dataset

    def friendly(file: Path) -> bool:
        state = load(file)
        return follows_recipe(state, stages) and state["dataset"]["config"] == dataset

    fits = {name: lambda file, c=config: made_by(file, c) for name, config in configs.items()}
    fits[FRIENDLY_MODEL] = friendly
    for name, path in paths.items():
        shipped = SHIPPED.get(name)
        if path.is_file() and (
            not fits[name](path)  # another profile's, recipe's or dataset's
            or (name in retrain and "optimizer" not in load(path))  # a shipped copy
        ):
            path.unlink()
        if (
            not path.is_file()
            and name not in retrain
            and shipped is not None
            and shipped.is_file()
            and fits[name](shipped)
        ):
            write_bytes_atomic(path, shipped.read_bytes())

    for name, config in configs.items():
        train(out / "data", paths[name], config, device=device, progress=progress)

    # The earlier stages are written only when they are trained here (not with the
    # shipped checkpoint): models/cnn_patch_smooth_stage1.pt, …
    path = paths[FRIENDLY_MODEL]
    if path.is_file() and load(path)["epoch"] >= stages[-1].epochs:
        return paths
    init = digest = None  # the stage before: its checkpoint and its weights' digest
    for i, stage in enumerate(stages):
        last = i == len(stages) - 1
        file = path if last else Path(out) / "models" / f"{FRIENDLY_MODEL}_stage{i + 1}.pt"
        stage = stage if digest is None else replace(stage, init=digest)
        if file.is_file() and not made_by(file, stage):  # another recipe's, or begun elsewhere
            file.unlink()
        state = train(out / "data", file, stage, init=init, device=device, progress=progress)
        init, digest = file, weights_digest(state["model"])
    return paths


def probe_input(size: int = 64):
    """A fixed input ``(1, 3, size, size)`` float32 in [0, 1], the same on every machine,
    whose heatmaps a shipped checkpoint's card records (a load check; ``size``: the
    backbone's input size in pixels)."""
    import torch

    _checks.integer(size, "size", minimum=1)
    return torch.linspace(0.0, 1.0, 3 * size * size).reshape(1, 3, size, size).flip(-1)


def ship(checkpoint, data_dir, target: Path, *, half: bool = False) -> dict:
    """Write the finished checkpoint ``checkpoint`` (trained on ``data_dir``) to ``target``
    without its optimiser state, with ``half`` its floating-point weights as float16 (half
    the file; :func:`kpstudy.models.training.load_checkpoint` loads them into a float32
    model), and its card ``target.json``: the recipe (and the earlier stages',
    ``lineage``, earliest first), the dataset, the test-split metrics of
    :func:`kpstudy.models.evaluation.evaluate` and the heatmaps' sum and absolute sum on
    :func:`probe_input` at the backbone's input size, both of the weights written. Nothing
    is written unless all of it is. Returns the card."""
    import tempfile

    import torch

    from kpstudy.models.evaluation import evaluate
    from kpstudy.models.training import load_checkpoint

    _, state = load_checkpoint(checkpoint)
    if state["epoch"] < state["config"]["epochs"]:
        raise ValueError(f"checkpoint: {checkpoint} is not finished")
    state = {k: v for k, v in state.items() if k not in ("optimizer", "scheduler")}
    state["dataset"] = dict(state["dataset"], path=None)  # no path of this machine
    if half:
        model = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
        if not all(bool(torch.isfinite(v).all()) for v in model.values()):
            raise ValueError(f"half: {checkpoint} holds weights beyond float16's range")
        state["model"] = model
    buffer = io.BytesIO()
    torch.save(state, buffer)
    with tempfile.TemporaryDirectory() as folder:  # what is evaluated is what is written
        written = Path(folder) / "shipped.pt"
        written.write_bytes(buffer.getvalue())
        backbone, _ = load_checkpoint(written)
        summary, _ = evaluate(written, data_dir, "test")
    with torch.no_grad():
        h = backbone(probe_input(backbone.input_size)).double()
    card = {
        "recipe": state["config"],
        "lineage": state.get("lineage", []),
        "dataset": state["dataset"],
        "test": summary.to_dict(orient="records"),
        "probe": {"sum": float(h.sum()), "abs_sum": float(h.abs().sum())},
    }
    write_bytes_atomic(target, buffer.getvalue())
    write_text_atomic(target.with_suffix(".json"), json.dumps(card, indent=1) + "\n")
    return card


def run_notebooks(
    prof: Profile,
    out: Path,
    *,
    scheduler: str | None = None,
    progress: bool = True,
    only=None,
) -> list[Path]:
    """Execute every study notebook (of ``only``'s names, when given) whose parameters or
    inputs changed."""
    out = Path(out).resolve()
    models = {k: str(p.resolve()) for k, p in checkpoints(out).items()}
    data_dir = str(out / "data")
    readings = list(prof.tolerance_units)
    campaign = dict(workers=prof.workers, scheduler=scheduler, method=prof.method, nodes=prof.nodes)
    cnn_campaign = dict(
        data_dir=data_dir,
        checkpoints={name: models[name] for name in ("cnn", FRIENDLY_MODEL)},
        seeds=prof.seeds,
        timeout=prof.timeout,
        pose_bound=prof.local_pose_bound,
        allocation=prof.allocation,
        tolerance_units=readings,
        **campaign,
    )
    parameters = {
        "01_data": dict(data_dir=data_dir),
        "02_training": dict(data_dir=data_dir, checkpoints=models),
        "03_symmetry": dict(
            data_dir=data_dir, checkpoint=models[prof.symmetry_backbone], images=prof.figure_images
        ),
        "04_allocation": dict(data_dir=data_dir, images=prof.figure_images, seed=prof.seed),
        "05_probabilistic": dict(
            image_size=prof.dataset_size,
            images=prof.images,
            samples=prof.samples,
            seed=prof.seed,
            tolerance_units=readings,
            workers=os.cpu_count() or 1,
        ),
        "06_local": cnn_campaign,
        "07_global": dict(cnn_campaign, pose_bound=prof.global_pose_bound),
        "08_resnet": dict(
            data_dir=data_dir,
            checkpoint=models["resnet18"],
            seeds=prof.resnet_seeds,
            timeout=prof.resnet_timeout,
            tolerance_units=readings,
            pose_bound=prof.resnet_pose_bound,
            **campaign,
        ),
    }
    done = out / "notebooks"
    done.mkdir(parents=True, exist_ok=True)
    executed = []
    for name, params in parameters.items():
        if only is not None and name not in only:
            continue
        params = {"out": str(out), **params}
        source = NOTEBOOKS / f"{name}.ipynb"
        target = done / f"{name}.ipynb"
        stamp = done / f"{name}.json"
        signature = _signature(source, params)
        if target.is_file() and stamp.is_file() and json.loads(stamp.read_text()) == signature:
            print(f"[reproduce] {name}: current, skipped", flush=True)
            continue
        stamp.unlink(missing_ok=True)
        print(f"[reproduce] {name}: running", flush=True)
        execute_notebook(source, target, params, done / f"{name}.kernel.log")
        write_text_atomic(stamp, json.dumps(signature, indent=1) + "\n")
        executed.append(target)
    return executed


def execute_notebook(source: Path, target: Path, params: dict, log: Path, cwd=NOTEBOOKS) -> None:
    """Run the notebook ``source`` with ``params`` into ``target`` under papermill, in a
    kernel of its own (:func:`kernel_manager`, its stderr to ``log``; ``_ipc_kernel()``)
    started in ``cwd``.

    Ctrl-C reaches the kernel too (the terminal signals the whole process group), which
    then answers the running cell with an error that nothing awaits any more: asyncio
    would print it, a traceback, when the process ends. That one report is dropped; the
    ``KeyboardInterrupt`` goes on to the caller."""
    import tempfile

    import papermill

    with tempfile.TemporaryDirectory(prefix="kpstudy-kernel-") as sockets:
        try:
            papermill.execute_notebook(
                str(source),
                str(target),
                parameters=params,
                cwd=str(cwd),
                progress_bar=False,
                kernel_name="python3",
                config=_ipc_kernel(sockets),
                kernel_manager_class=kernel_manager(log),
            )
        except KeyboardInterrupt:
            _drop_interrupted_cell_reports()
            raise


def _drop_interrupted_cell_reports() -> None:
    """Make the event loop that papermill runs on (jupyter_core's, this thread's) drop its
    "Task exception was never retrieved" report of a cell that Ctrl-C stopped; every
    other report goes to the handler it had."""
    from jupyter_core.utils import ensure_event_loop
    from nbclient.exceptions import CellExecutionError

    loop = ensure_event_loop()
    previous = loop.get_exception_handler()

    def handler(loop, context):
        error = context.get("exception")
        if isinstance(error, CellExecutionError) and error.ename == "KeyboardInterrupt":
            return
        if previous is None:
            loop.default_exception_handler(context)
        else:
            previous(loop, context)

    loop.set_exception_handler(handler)


def kernel_manager(log: Path):
    """A jupyter_client ``AsyncKernelManager`` class whose kernel process writes its own
    stderr (IPKernel's log: e.g. its messages when Ctrl-C stops a notebook) to the file
    ``log`` instead of the terminal. Cell outputs travel over the kernel's sockets into the
    executed notebook as before."""
    from jupyter_client import AsyncKernelManager

    class LoggedKernelManager(AsyncKernelManager):
        async def start_kernel(self, **kw):  # kw reach subprocess.Popen
            with open(log, "ab") as stream:  # the kernel keeps its own copy of the file
                return await super().start_kernel(**kw, stderr=stream)

    return LoggedKernelManager


def _ipc_kernel(folder: str):
    """nbclient's kernel-manager settings (a traitlets ``Config``) for a kernel that talks
    over Unix sockets ``folder/kernel-1…5`` (a private temporary folder) instead of
    unencrypted TCP on localhost: no local user can listen in, and IPKernel has no
    eavesdropping warning to print. Where Unix sockets are missing (Windows), TCP."""
    from traitlets.config import Config

    if os.name != "posix":
        return Config()
    return Config({"KernelManager": {"transport": "ipc", "ip": os.path.join(folder, "kernel")}})


def _signature(notebook: Path, params: dict) -> dict:
    """What a notebook's outputs depend on: its source, kpstudy's and data_gen's code
    (:func:`kpstudy.io.source_fingerprint`), its parameters and the files named in them
    (size and modification time)."""
    files = {}
    for value in _values(params):
        path = Path(value) if isinstance(value, str) else None
        if path is None:
            continue
        members = [path] if path.is_file() else []
        if (path / "annotations.json").is_file():  # a dataset and its perturbation sets
            members = [path / "annotations.json", *sorted(path.glob("perturbations/*/meta.json"))]
        for member in members:
            stat = member.stat()
            files[str(member)] = [stat.st_size, stat.st_mtime_ns]
    return {
        "notebook": hashlib.sha256(notebook.read_bytes()).hexdigest(),
        "code": source_fingerprint(),
        "parameters": params,
        "files": files,
    }


def _values(params: dict):
    for value in params.values():
        if isinstance(value, dict):
            yield from _values(value)
        else:
            yield value
