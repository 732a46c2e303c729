"""The study's verification instances as a VNN-COMP benchmark (issue 28).

:func:`export_benchmark` writes each instance of a campaign grid
(:func:`kpstudy.study.campaign.grid`) in the layout of the VNN-COMP benchmarks, so that any
verifier that reads ONNX + VNN-LIB runs exactly what :func:`kpstudy.certify.hull.certify`
verifies::

    DIR/onnx/NAME.onnx        the proxy with the hull folded in and, by default, each
                              keypoint's worst margin computed in it (kpstudy.verify.export)
    DIR/vnnlib/NAME.vnnlib    the input set and the violation of "each keypoint's cell wins"
                              (one disjunct per keypoint by default)
    DIR/instances.csv         onnx/NAME.onnx,vnnlib/NAME.vnnlib,TIMEOUT (no header)
    DIR/reference.csv         kpstudy's own verdict per instance (with ``reference_nodes``)
    DIR/README.md             how the files were made and what each instance means

Each instance's vertices are those of the campaign (:func:`data_gen.perturb.hull_vertices`
with the campaign's default ``hull_seed``), its proxy, hull and spec those of
:func:`kpstudy.certify.allocation_method.build_instance` under the chosen tolerance reading. With
``reference_nodes``, :func:`kpstudy.verify.bab.verify` decides each instance within that node
budget (the campaign's verdict for that budget, on any machine), and ``mix`` keeps the
grid's instances, in order, only while their verdict's class (``holds``, ``violated``,
``unknown``) has fewer than ``mix``: a benchmark of proofs, refutations and hard cases.
The files depend only on the arguments, the checkpoint, the dataset and the code (no
dates, no paths but the command's own; only reference.csv's seconds vary): a rerun
writes the same bytes. The folder is built beside ``DIR`` (``.DIR.partial``; an
interrupted run leaves it there, and the next run rewrites it) and moved onto ``DIR``
at the end: ``DIR`` appears complete or not at all.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import math
import os
import shutil
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

__all__ = ["DTYPES", "REFERENCE_METHOD", "VERDICTS", "export_benchmark", "instance_name"]

#: The exported networks' dtypes by name (``dtype`` of :func:`export_benchmark`).
DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: The bound method of the reference verdicts (:func:`kpstudy.verify.bab.verify`'s default).
REFERENCE_METHOD = "auto"
#: The classes of reference verdicts that ``mix`` balances: proofs, refutations, hard cases.
VERDICTS = ("holds", "violated", "unknown")
#: Why an instance whose pixel grid alone exceeds the tolerance is not exported.
_NOT_CERTIFIABLE = (
    "not certifiable at this heatmap resolution (the nearest pixels' first-order pose "
    "error is {:.3g} × ε/κ)"
)


#: Why an instance whose cells leave no keypoint a competing cell is not exported.
_NOTHING_TO_VERIFY = (
    "nothing to verify: every keypoint's cell covers its whole heatmap (the property holds "
    "trivially)"
)


class _NothingWritten(Exception):
    """No instance of the grid could be built (the staging folder is removed)."""


@dataclass(frozen=True)
class _Options:
    """The export options of :func:`export_benchmark`, checked on construction (one line
    naming the first one wrong; ``timeout`` becomes float seconds), as its README and its
    staging config record them."""

    timeout: float
    input_form: str
    vnnlib_version: str
    dtype: str
    property_form: str
    tolerance_units: str
    reference_nodes: int | None
    mix: int | None

    def __post_init__(self) -> None:  # in the order of export_benchmark's signature
        from kpstudy import _checks
        from kpstudy.pose.allocation import TOLERANCE_UNITS
        from kpstudy.verify.export import INPUT_FORMS, PROPERTY_FORMS, VNNLIB_VERSIONS

        timeout = _checks.seconds(self.timeout, "timeout")
        if not math.isfinite(timeout):  # written into instances.csv: no cap is not a timeout
            raise ValueError(f"timeout: expected finite seconds > 0, got {timeout!r}")
        object.__setattr__(self, "timeout", timeout)
        _checks.choice(self.input_form, "input_form", INPUT_FORMS)
        _checks.choice(self.vnnlib_version, "vnnlib_version", VNNLIB_VERSIONS)
        _checks.choice(self.dtype, "dtype", DTYPES)
        _checks.choice(self.property_form, "property_form", PROPERTY_FORMS)
        _checks.choice(self.tolerance_units, "tolerance_units", TOLERANCE_UNITS)
        _checks.integer(self.reference_nodes, "reference_nodes", minimum=1, optional=True)
        _checks.integer(self.mix, "mix", minimum=1, optional=True)
        if self.mix is not None and self.reference_nodes is None:
            raise ValueError("mix: selects by kpstudy's verdicts; give reference_nodes too")


@dataclass(frozen=True)
class _Outcome:
    """What an export made of the grid: its ``instances`` and their ``names``, the names
    ``written`` (in order) and their ``sizes`` (n inputs, cells, outputs, disjuncts), the
    ``skipped`` ``(name, reason)``, the ``reference`` verdicts, the ``unmixed``
    ``(name, status)`` and the ``unexamined`` count."""

    instances: list
    names: list
    written: list
    sizes: dict
    skipped: list
    reference: dict
    unmixed: list
    unexamined: int


def _num(x: float) -> str:
    """``x`` in positional notation, no trailing point (``1``, ``1.5``, ``0.0005``)."""
    return np.format_float_positional(float(x), unique=True, trim="-")


def instance_name(instance) -> str:
    """A file-name stem for a :class:`kpstudy.study.campaign.Instance`: kind, seed image, hull
    (``m2_ov`` / ``m2_nov``, or ``l2`` for a level), ``a<α>_k<κ>``, e.g.
    ``blocks_481_m2_ov_a1_k1.5`` or ``contrast_481_l0.005_a1_k1``."""
    if instance.level is not None:
        hull = f"l{_num(instance.level)}"
    else:
        hull = f"m{instance.m}_{'ov' if instance.overlapping else 'nov'}"
    allocation = f"a{_num(instance.alpha)}_k{_num(instance.kappa)}"
    return f"{instance.kind}_{instance.image_id}_{hull}_{allocation}"


def _sha256(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _check_out(out) -> Path:
    """``out`` may be missing or an empty folder (one line naming ``out`` otherwise)."""
    from kpstudy.io import check_writable

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"out: {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        raise FileExistsError(f"out: {out} is not empty; expected a new or empty folder")
    return check_writable(out, "out")


def export_benchmark(
    checkpoint,
    data_dir,
    out,
    instances,
    *,
    timeout: float = 60.0,
    input_form: str = "box",
    vnnlib_version: str = "1.0",
    dtype: str = "float32",
    property_form: str = "compact",
    tolerance_units: str = "heatmap",
    reference_nodes: int | None = None,
    mix: int | None = None,
    command: str | None = None,
    progress: bool = False,
) -> dict:
    """Write ``instances`` as a VNN-COMP benchmark folder ``out``.

    Parameters
    ----------
    checkpoint : path
        A kpstudy checkpoint (``python -m kpstudy train``).
    data_dir : path
        The data_gen dataset with the instances' perturbation sets.
    out : path
        The benchmark folder; must not exist or be empty. Built beside it and moved onto
        it when every instance is written.
    instances : list of kpstudy.study.campaign.Instance
        Usually :func:`kpstudy.study.campaign.grid`'s; duplicates are written once.
    timeout : float
        Seconds per instance, the third column of ``instances.csv``.
    input_form, vnnlib_version :
        Of :func:`kpstudy.verify.export.export_instance` (``'box'`` / ``'simplex'``,
        ``'1.0'`` / ``'2.0'``).
    dtype : {'float32', 'float64'}
        Precision of the ONNX graphs.
    property_form : {'compact', 'full'}
        Of :func:`~kpstudy.verify.export.export_instance`: each keypoint's worst margin in
        the graph and one disjunct per keypoint (default), or the proxy's cells as the
        output and one disjunct per competing cell.
    tolerance_units : {'heatmap', 'paper'}
        The allocation's reading of the tolerances
        (:data:`kpstudy.pose.allocation.TOLERANCE_UNITS`), which sets each keypoint's
        cells: ``'heatmap'`` (sound to first order; on the 64×64 CNN its instances tend
        to be violated at the seed image) or the paper's, larger cells.
    reference_nodes : int, optional
        Decide each instance with :func:`kpstudy.verify.bab.verify` (method
        :data:`REFERENCE_METHOD`, this node budget, no time budget) and write
        ``reference.csv``: ``name,status,time,nodes,method,max_nodes`` (header; seconds
        of this machine). None (default): no verification, no reference.csv.
    mix : int, optional
        Walk the grid in order and keep an instance only while its reference verdict's
        class (:data:`VERDICTS`) holds fewer than ``mix`` kept ones; stop once every
        class has ``mix``. Needs ``reference_nodes``. README.md lists the verdicts of the
        instances left out and the count never examined.
    command : str, optional
        The command line to record in README.md (default: a call of this function).
    progress : bool
        A progress bar.

    Returns
    -------
    dict
        ``out`` (Path), ``written`` (instance names, in order), ``skipped``
        (``(name, reason)`` of the seeds
        :func:`kpstudy.certify.allocation_method.build_instance` refuses: no valid nominal
        pose, a keypoint outside the heatmap, and of the instances that are not certifiable
        at the heatmap's resolution or have nothing to verify: every keypoint's cell its
        whole heatmap), ``reference`` (name → ``(status, seconds, nodes)`` of the written
        instances; empty without ``reference_nodes``), ``unmixed`` (``(name, status)`` of
        the instances ``mix`` left out) and ``unexamined`` (how many of the grid's instances
        ``mix`` never built).

    Raises
    ------
    ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, PermissionError
        One line naming the argument (``checkpoint``, ``data``, ``out``, ``timeout``,
        ``input_form``, ``vnnlib_version``, ``dtype``, ``property_form``,
        ``tolerance_units``, ``reference_nodes``, ``mix``, ``instances``), before anything
        is written.
    """
    checkpoint, data_dir = _check_sources(checkpoint, data_dir)
    options = _Options(
        timeout=timeout,
        input_form=input_form,
        vnnlib_version=vnnlib_version,
        dtype=dtype,
        property_form=property_form,
        tolerance_units=tolerance_units,
        reference_nodes=reference_nodes,
        mix=mix,
    )
    instances = _check_instances(instances)
    out = _check_out(out)
    command = command or (
        f"kpstudy.study.export_benchmark({str(checkpoint)!r}, {str(data_dir)!r}, {str(out)!r}, …)"
    )
    outcome = _export(checkpoint, data_dir, out, instances, options, command, progress)
    return {
        "out": out,
        "written": outcome.written,
        "skipped": outcome.skipped,
        "reference": outcome.reference,
        "unmixed": outcome.unmixed,
        "unexamined": outcome.unexamined,
    }


def _check_sources(checkpoint, data_dir) -> tuple[Path, Path]:
    """``checkpoint`` a file and ``data_dir`` a data_gen dataset, as Paths (one line
    naming ``checkpoint`` or ``data`` otherwise)."""
    checkpoint, data_dir = Path(checkpoint), Path(data_dir)
    if not checkpoint.is_file():
        raise FileNotFoundError(f"checkpoint: no file at {checkpoint}")
    if not (data_dir / "annotations.json").is_file():
        raise FileNotFoundError(f"data: no data_gen dataset at {data_dir}")
    return checkpoint, data_dir


def _check_instances(instances) -> list:
    """``instances`` in order without duplicates (one line naming ``instances`` if there
    are none)."""
    instances = list(dict.fromkeys(instances))
    if not instances:
        raise ValueError("instances: the grid is empty; nothing to export")
    return instances


def _export(
    checkpoint: Path,
    data_dir: Path,
    out: Path,
    instances: list,
    options: _Options,
    command: str,
    progress: bool,
) -> _Outcome:
    """Build the benchmark in ``out``'s staging folder and move it onto ``out``: the
    instances, then instances.csv, reference.csv and README.md. A grid of which no
    instance can be written leaves nothing behind (a ``ValueError`` naming
    ``instances``); any other failure leaves the staging folder."""
    from kpstudy.io import staged_directory, write_text_atomic
    from kpstudy.study.campaign import Settings, _context, provenance

    settings = Settings(
        str(checkpoint),
        str(data_dir),
        timeout=options.timeout,
        nodes=options.reference_nodes,
        tolerance_units=options.tolerance_units,
    )
    backbone, seed_of = _context(str(checkpoint), str(data_dir))  # refuses a bad checkpoint
    origin = provenance(settings)
    config = {"provenance": origin, "instances": [i.key for i in instances], **asdict(options)}
    names = [instance_name(i) for i in instances]
    build = partial(
        _build, backbone, seed_of, data_dir, settings.hull_seed, options.tolerance_units
    )
    staged = None
    try:
        with staged_directory(out, config) as (staging, _):
            staged = staging
            outcome = _write_instances(staging, instances, names, build, options, progress)
            _write_lists(staging, options, outcome)
            header = _readme_header(command, checkpoint, data_dir, origin, options, outcome)
            readme = _readme(header, options, outcome)
            write_text_atomic(staging / "README.md", readme)
    except _NothingWritten as exc:  # input the grid cannot use: leave nothing behind
        shutil.rmtree(staged, ignore_errors=True)
        raise ValueError(str(exc)) from None
    return outcome


def _write_instances(
    staging: Path, instances: list, names: list, build, options: _Options, progress: bool
) -> _Outcome:
    """Walk ``instances`` (named ``names``) in order: ``build`` each (:func:`_build`), with
    ``options.reference_nodes`` decide it (:func:`_reference_verdict`) and keep it only
    while ``options.mix`` allows, and write those kept into ``staging``
    (:func:`_write_instance`). What the walk made of them as an :class:`_Outcome`;
    :class:`_NothingWritten` if it wrote none."""
    from tqdm.auto import tqdm

    written, skipped, sizes, reference, unmixed = [], [], {}, {}, []
    kept = dict.fromkeys(VERDICTS, 0)
    unexamined = 0
    for sub in ("onnx", "vnnlib"):
        (staging / sub).mkdir(exist_ok=True)
    work = staging / ".instance"
    mix = options.mix
    walk = tqdm(list(zip(instances, names)), desc="instances", unit="inst", disable=not progress)
    for index, (instance, name) in enumerate(walk):
        if mix is not None and min(kept.values()) >= mix:
            unexamined = len(instances) - index
            break
        built, reason = build(instance)
        if built is None:
            skipped.append((name, reason))
            continue
        if options.reference_nodes is not None:
            status, seconds, nodes = _reference_verdict(built, options.reference_nodes)
            if mix is not None and kept[status] >= mix:
                unmixed.append((name, status))
                continue
            kept[status] += 1
            reference[name] = (status, seconds, nodes)
        size = _write_instance(staging, work, name, built, options)
        written.append(name)
        sizes[name] = size
    if work.exists():
        shutil.rmtree(work)
    if not written:
        raise _NothingWritten(
            "instances: no seed image of the grid can be certified ("
            + "; ".join(f"{n}: {r}" for n, r in skipped[:3])
            + ")"
        )
    return _Outcome(instances, names, written, sizes, skipped, reference, unmixed, unexamined)


def _build(backbone, seed_of, data_dir: Path, hull_seed: int, tolerance_units: str, instance):
    """``(built, None)``: ``instance``'s proxy, hull and spec
    (:func:`kpstudy.certify.allocation_method.build_instance`'s), or ``(None, reason)``
    for one left out: a seed it refuses, one not certifiable at the heatmap's resolution,
    one with nothing to verify."""
    from kpstudy.certify.allocation_method import build_instance
    from kpstudy.study.campaign import instance_vertices

    vertices = instance_vertices(instance, data_dir, hull_seed)
    try:
        built = build_instance(
            backbone,
            vertices,
            seed_of(instance.image_id),
            alpha=instance.alpha,
            kappa=instance.kappa,
            tolerance_units=tolerance_units,
        )
    except ValueError as exc:  # a seed that cannot be certified: no instance
        return None, str(exc)
    if not built.feasible:
        return None, _NOT_CERTIFIABLE.format(built.first_order)
    if built.spec.n_rows == 0:
        return None, _NOTHING_TO_VERIFY
    return built, None


def _reference_verdict(built, max_nodes: int) -> tuple:
    """kpstudy's ``(status, seconds, nodes)`` on ``built``: :func:`kpstudy.verify.verify`
    with :data:`REFERENCE_METHOD`, ``max_nodes`` and no time budget."""
    from kpstudy.verify import verify

    result = verify(
        built.proxy,
        built.hull,
        built.spec,
        method=REFERENCE_METHOD,
        timeout=math.inf,
        max_nodes=max_nodes,
    )
    return result.status, result.time, result.nodes


def _write_instance(staging: Path, work: Path, name: str, built, options: _Options) -> tuple:
    """Write ``built`` as ``onnx/NAME.onnx`` and ``vnnlib/NAME.vnnlib`` in ``staging``
    (made in the scratch folder ``work``; the pair is complete once the ONNX file is
    there); its sizes: n inputs, cells, outputs, disjuncts."""
    from kpstudy.io import write_text_atomic
    from kpstudy.verify.export import export_instance

    if work.exists():
        shutil.rmtree(work)
    info = export_instance(
        work,
        built.proxy,
        built.hull,
        built.spec,
        input_form=options.input_form,
        dtype=DTYPES[options.dtype],
        vnnlib_version=options.vnnlib_version,
        property_form=options.property_form,
    )
    text = (work / "spec.vnnlib").read_text()
    write_text_atomic(
        staging / "vnnlib" / f"{name}.vnnlib", text.replace("model.onnx", f"onnx/{name}.onnx")
    )
    os.replace(work / "model.onnx", staging / "onnx" / f"{name}.onnx")  # the pair is complete
    return (info["n_inputs"], built.spec.n_outputs, info["n_outputs"], info["n_disjuncts"])


def _write_lists(staging: Path, options: _Options, outcome: _Outcome) -> None:
    """``instances.csv`` (no header) and, with ``options.reference_nodes``,
    ``reference.csv`` of ``outcome``'s written instances in ``staging``."""
    from kpstudy.io import write_text_atomic

    rows = [f"onnx/{n}.onnx,vnnlib/{n}.vnnlib,{_num(options.timeout)}" for n in outcome.written]
    write_text_atomic(staging / "instances.csv", "\n".join(rows) + "\n")
    if options.reference_nodes is not None:
        rows = ["name,status,time,nodes,method,max_nodes"] + [
            f"{n},{status},{seconds:.3f},{nodes},{REFERENCE_METHOD},{options.reference_nodes}"
            for n, (status, seconds, nodes) in outcome.reference.items()
        ]
        write_text_atomic(staging / "reference.csv", "\n".join(rows) + "\n")


def _readme(header: list[str], options: _Options, outcome: _Outcome) -> str:
    """The benchmark's README.md: its ``header`` (:func:`_readme_header`), what an instance
    is as ``options`` export it, and the table of ``outcome``'s instances."""
    lines = [
        *header,
        *_readme_instance(options),
        *_readme_reference(options, outcome),
        *_readme_mix(options, outcome),
        *_readme_table(options, outcome),
        *_readme_left_out(outcome),
    ]
    return "\n".join(lines) + "\n"


def _verdict_counts(outcome: _Outcome) -> dict:
    """How many of ``outcome``'s reference verdicts fall in each class of :data:`VERDICTS`."""
    return {v: sum(r[0] == v for r in outcome.reference.values()) for v in VERDICTS}


def _readme_header(
    command: str,
    checkpoint: Path,
    data_dir: Path,
    origin: dict,
    options: _Options,
    outcome: _Outcome,
) -> list[str]:
    """README.md's title, how ``command`` made the benchmark from ``checkpoint`` and
    ``data_dir`` (their digests in ``origin``, :func:`kpstudy.study.campaign.provenance`'s):
    the versions, digests and options, the layout."""
    from kpstudy import __version__ as version
    from kpstudy.io import source_fingerprint

    code = source_fingerprint()
    versions = ", ".join(f"{p} {importlib.metadata.version(p)}" for p in ("torch", "onnx", "numpy"))
    return [
        "# kpstudy keypoint-proxy verification benchmark",
        "",
        "Made with",
        "",
        "```",
        command,
        "```",
        "",
        f"- kpstudy {version} (code fingerprint `{code}`; {versions})",
        f"- checkpoint `{checkpoint.name}`, SHA-256 `{origin['checkpoint']}`",
        f"- dataset `{data_dir.name}`, SHA-256 `{origin['dataset']}` (over its "
        "`annotations.json` and the perturbation sets' `meta.json`)",
        f"- {len(outcome.sizes)} instances, input form `{options.input_form}`, property form "
        f"`{options.property_form}`, ONNX {options.dtype}, VNN-LIB {options.vnnlib_version}, "
        f"timeout {_num(options.timeout)} s each, tolerance reading `{options.tolerance_units}`",
        "",
        "Layout as in the VNN-COMP benchmarks: `onnx/NAME.onnx`, `vnnlib/NAME.vnnlib`, and "
        "`instances.csv` with one row `onnx/NAME.onnx,vnnlib/NAME.vnnlib,TIMEOUT` per "
        "instance (no header).",
        "",
    ]


def _readme_instance(options: _Options) -> list[str]:
    """README.md's "What an instance is": the input set, the network, the property (as
    ``options`` export them) and the names."""
    form = {
        "box": "`u` in the box [0, 1]^n, mapped exactly onto the simplex inside the network "
        "(a ReLU sorting layer, then the spacings λ₁ = u₍₁₎, λᵢ = u₍ᵢ₎ − u₍ᵢ₋₁₎): every "
        "verifier that takes box inputs runs the exact hull",
        "simplex": "`lam` = λ with λ ≥ 0 and the linear input constraint Σ λ ≤ 1 (only "
        "verifiers that accept linear input constraints read it)",
    }[options.input_form]
    property_text = {
        "compact": "The network ends in each verified keypoint's worst margin, the least "
        "`y_t − y_j` over its other cells j (t: its target cell; the minimum a ReLU tree, "
        "`min(a, b) = a − relu(a − b)`, of ONNX `Slice`, `Sub`, `Concat`, `Reshape` and "
        "`Relu`, no `Gather`): "
        "one output `Y_i` per verified keypoint, in keypoint order (the VNN-LIB header "
        "lists them), and one disjunct `Y_i ≤ 0` per output, the same verdict as one "
        "disjunct `Y_j ≥ Y_t` per competing cell (property form `full`) in a file of a few "
        "kilobytes.",
        "full": "The network's output `y` is the cells of all keypoints, and the violation "
        "is one disjunct `Y_j ≥ Y_t` per other cell j of a keypoint with target t.",
    }[options.property_form]
    return [
        "## What an instance is",
        "",
        "One seed image of the dataset's test split and `m` perturbed images of it (the "
        "perturbation kind: occluding objects, 3×3 blocks of random values, or brightness / "
        "contrast ±level), resized to the model input and normalised: the n + 1 = m + 1 "
        "vertices of a convex hull of images. The input set is that hull, exactly: the "
        "network's leading layers map the input onto the barycentric weights w of the "
        "vertices and compute `w @ V` with the vertices themselves. Its input is " + form + ".",
        "",
        "The network is the study's *proxy*: the trained heatmap backbone, then per "
        "keypoint an average pooling of its heatmap channel into cells of side 2δv + 1 "
        "centred on the rounded ground-truth keypoint (the tolerances δv of the allocation "
        "`κ |M| δv ≤ α ε` at the seed's nominal pose, ε = α·[10°, 10°, 10°, 4, 4, 20 m], "
        + {
            "heatmap": "read in heatmap pixels around the exact keypoints: sound to first order",
            "paper": "the paper's reading: allocated per image pixel and used as heatmap "
            "pixels, larger cells",
        }[options.tolerance_units]
        + "), the cells of all keypoints concatenated. Its batch norms are folded into the "
        "convolutions, every value has a static shape (batch 1) and every node input a "
        "name, and the graph passes `onnx.checker`'s full check: ONNX importers such as "
        "onnx2pytorch (α,β-CROWN's, NeuralSAT's) read it.",
        "",
        "The property is that every keypoint's target cell (the one holding its ground "
        "truth) has the largest pooled value of its keypoint's cells, on every image of the "
        "hull. The VNN-LIB file states its *violation*: `unsat` means the property holds "
        "(kpstudy's `holds`), a satisfying input is a counterexample (`violated`). Ties "
        "count as violations. " + property_text,
        "",
        "Names: `KIND_IMAGEID_HULL_aALPHA_kKAPPA`, HULL `mM_ov` / `mM_nov` (m perturbed "
        "images overlapping the airplane or not) or `lLEVEL` (brightness b, contrast c).",
        "",
    ]


def _readme_reference(options: _Options, outcome: _Outcome) -> list[str]:
    """README.md's "Reference verdicts" (none without ``options.reference_nodes``): how
    reference.csv was decided and its counts."""
    if options.reference_nodes is None:
        return []
    counts = _verdict_counts(outcome)
    return [
        "## Reference verdicts",
        "",
        "`reference.csv` (`name,status,time,nodes,method,max_nodes`) holds kpstudy's own "
        f"verdict on each instance: `kpstudy.verify.verify`, method `{REFERENCE_METHOD}`, "
        f"a budget of {options.reference_nodes} branch-and-bound nodes and no time budget "
        "(the verdict does not depend on the machine; the seconds are this machine's), on the "
        "float32 torch proxy. `holds` is `unsat`, `violated` is `sat`, `unknown` means "
        "the budget ran out: a hard case. Counts: "
        + ", ".join(f"{counts[v]} {v}" for v in VERDICTS)
        + ".",
        "",
    ]


def _readme_mix(options: _Options, outcome: _Outcome) -> list[str]:
    """README.md's paragraph on the ``mix`` selection (none without ``options.mix``):
    the rule, what it left out or never built, the classes it found empty."""
    if options.mix is None:
        return []
    counts = _verdict_counts(outcome)
    return [
        "Selection (`mix` = " + str(options.mix) + "): the grid was walked in order and an "
        "instance kept only while its verdict's class (holds, violated, unknown) had "
        f"fewer than {options.mix} kept instances; the walk stopped once every class had "
        f"{options.mix}. "
        + (
            f"Left out for a full class: {len(outcome.unmixed)} (listed below)"
            if outcome.unmixed
            else "None was left out for a full class"
        )
        + (
            f", and the grid's last {outcome.unexamined} were never built."
            if outcome.unexamined
            else "; the whole grid was examined."
        )
        + "".join(
            f" No `{v}` instance was found: the class is empty." for v in VERDICTS if not counts[v]
        ),
        "",
    ]


def _readme_table(options: _Options, outcome: _Outcome) -> list[str]:
    """README.md's "Instances": a row per written instance (its grid point, sizes and,
    with ``options.reference_nodes``, kpstudy's verdict and nodes)."""
    header = "| name | kind | image | m | overlapping | level | α | κ | n | cells | outputs |"
    header += " disjuncts |"
    if options.reference_nodes is not None:
        header += " kpstudy | nodes |"
    lines = ["## Instances", "", header, "|---" * header.count(" | ") + "|---|"]
    for instance, name in zip(outcome.instances, outcome.names):
        if name not in outcome.sizes:
            continue
        cells = [
            name,
            instance.kind,
            instance.image_id,
            "–" if instance.m is None else instance.m,
            "–" if instance.overlapping is None else instance.overlapping,
            "–" if instance.level is None else _num(instance.level),
            _num(instance.alpha),
            _num(instance.kappa),
            *outcome.sizes[name],
        ]
        if options.reference_nodes is not None:
            cells += [outcome.reference[name][0], outcome.reference[name][2]]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    return lines


def _readme_left_out(outcome: _Outcome) -> list[str]:
    """README.md's "Left out" (the seeds that cannot be certified) and "Not kept by the
    mix" (the instances of a full class), each only when there are some."""
    lines = []
    if outcome.skipped:
        lines += ["", "## Left out", "", "Seed images that cannot be certified:", ""]
        lines += [f"- {name}: {reason}" for name, reason in outcome.skipped]
    if outcome.unmixed:
        lines += ["", "## Not kept by the mix", "", "Their class was full (kpstudy's verdict):"]
        lines += [""] + [f"- {name}: {status}" for name, status in outcome.unmixed]
    return lines
