"""``results/<profile>/REPORT.md``: every table and figure of a run, the paper beside ours,
and a short reading of the trends computed from the tables (never written by hand).

:func:`write_report` reads what the notebooks wrote under ``tables/`` and ``figures/``;
a missing table or figure is listed as missing rather than skipped silently.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pandas as pd

from kpstudy.io import write_text_atomic
from kpstudy.tables import reading_comparison

__all__ = ["SECTIONS", "campaign_readings", "t_prob_readings", "write_report"]

#: (title, notebook, tables, figures, what it reproduces)
SECTIONS = (
    (
        "F-data: dataset and perturbations",
        "01_data",
        ["f_data"],
        ["renders", "occluders", "perturbations"],
        "paper §8.1, Figs. 5–6",
    ),
    ("Trained backbones", "02_training", ["training"], ["training"], "paper §8.1"),
    ("F-sym: heatmap symmetry", "03_symmetry", ["f_sym"], ["f_sym"], "paper Fig. 8"),
    (
        "F-alloc and F-kps: allocated tolerances",
        "04_allocation",
        [],
        ["f_alloc", "f_kps"],
        "paper Figs. 9–10 (table: tables/f_alloc.csv)",
    ),
    (
        "T-prob: probabilistic soundness and completeness",
        "05_probabilistic",
        ["t_prob"],
        [],
        "paper Table 2",
    ),
    (
        "T-local: object occlusions, CNN",
        "06_local",
        ["t_local"],
        ["t_local", "t_local_pose_bound"],
        "paper Tables 3–4",
    ),
    (
        "T-global: brightness and contrast, CNN",
        "07_global",
        ["t_global"],
        ["t_global", "t_global_pose_bound"],
        "paper Tables 5–6",
    ),
    (
        "T-resnet: block occlusions, ResNet-18",
        "08_resnet",
        ["t_resnet"],
        ["t_resnet"],
        "paper §8.4",
    ),
)


def write_report(out, profile: dict | None = None) -> Path:
    """Assemble ``out/REPORT.md`` from ``out/tables`` and ``out/figures``."""
    out = Path(out)
    tables, figures = out / "tables", out / "figures"
    lines = [
        f"# kpstudy: {out.name} profile",
        "",
        "Written by `python -m kpstudy reproduce`; every number below comes from the tables "
        "beside this file (`tables/*.csv`), produced by the notebooks in `notebooks/`. Paper "
        "columns are the numbers of the paper (ModelVerification.jl on an RTX A4000).",
        "",
    ]
    if profile:
        lines += ["| setting | value |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in profile.items()]
        lines.append("")
    readers = {
        "t_prob": t_prob_readings,
        "t_local": _local,
        "t_global": _global,
        "t_resnet": _resnet,
    }
    for title, notebook, names, pictures, source in SECTIONS:
        lines += [f"## {title}", "", f"Notebook `notebooks/{notebook}.ipynb`; {source}.", ""]
        for name in names:
            md = tables / f"{name}.md"
            if not md.is_file():
                lines += [f"*Table `{name}` is missing (its notebook has not run).*", ""]
                continue
            lines += [md.read_text().rstrip(), ""]
            if name in readers:
                text = readers[name](pd.read_csv(tables / f"{name}.csv"))
                lines += ["**Reading.**", "", *[f"- {t}" for t in text], ""]
        for picture in pictures:
            png = figures / f"{picture}.png"
            lines += (
                [f"![{picture}](figures/{picture}.png)", ""]
                if png.is_file()
                else [f"*Figure `{picture}` is missing.*", ""]
            )
    return write_text_atomic(out / "REPORT.md", "\n".join(lines))


def _per_group(read, compare: tuple[str, str, str] | None = None):
    """``read(table)``, once per ``model`` and tolerance reading (its lines prefixed by
    them) when the table has them; with ``compare`` (ours, paper, name), first each
    model's sentence of :func:`kpstudy.tables.reading_comparison`."""

    def readings(table):
        keys = [c for c in ("model", "tolerance_units") if c in table]
        lines = []
        if compare is not None:
            models = table.groupby("model", sort=True) if "model" in table else [("", table)]
            for model, part in models:
                sentence = reading_comparison(part, *compare)
                if sentence:
                    lines.append((f"`{model}`: " if model else "") + sentence)
        for key, part in table.groupby(keys, sort=True) if keys else [((), table)]:
            key = key if isinstance(key, tuple) else (key,)
            prefix = "".join(
                f"`{v}`: " if k == "model" else f"'{v}' reading: " for k, v in zip(keys, key)
            )
            lines += [prefix + line for line in read(part)]
        return lines

    return readings


def t_prob_readings(table: pd.DataFrame) -> list[str]:
    """Does soundness rise with κ and fall with α; does completeness do the opposite?
    Per tolerance reading, after the sentence comparing the readings with the paper."""
    return _per_group(_t_prob, ("soundness", "paper_soundness", "Soundness"))(table)


def _t_prob(table: pd.DataFrame) -> list[str]:
    s = table.pivot(index="kappa", columns="alpha", values="soundness")
    c = table.pivot(index="kappa", columns="alpha", values="completeness")
    paper = table.pivot(index="kappa", columns="alpha", values="paper_soundness")
    rises = bool(np.all(np.diff(s.to_numpy(), axis=0) >= -1e-12))
    falls = bool(np.all(np.diff(c.to_numpy(), axis=0) <= 1e-12))
    return [
        f"Soundness {'never falls' if rises else 'does not always rise'} as κ grows "
        f"(range {s.to_numpy().min():.4g}–{s.to_numpy().max():.4g}; paper "
        f"{table.paper_soundness.min():.4g}–{table.paper_soundness.max():.4g}).",
        f"Completeness {'never rises' if falls else 'does not always fall'} as κ grows "
        f"(at most {c.to_numpy().max():.3g}; paper at most {table.paper_completeness.max():.3g}): "
        "independent per-keypoint tolerances are very conservative, as the paper says.",
        f"At κ = {s.index[0]:g}, soundness from α = {s.columns[0]:g} to {s.columns[-1]:g}: "
        f"{s.iloc[0, 0]:.4g} → {s.iloc[0, -1]:.4g} (paper {paper.iloc[0, 0]:.4g} → "
        f"{paper.iloc[0, -1]:.4g}).",
    ] + (
        [
            f"The same integer boxes read as heatmap pixels (the cells the verifier proves) "
            f"keep {table.soundness_true_units.min():.4g}–{table.soundness_true_units.max():.4g} "
            "of their vertices' poses in Ξ."
        ]
        if "soundness_true_units" in table and (table.get("tolerance_units") == "paper").all()
        else []
    )


def campaign_readings(table: pd.DataFrame, axes: dict[str, str], summary: bool = True) -> list[str]:
    """For each axis ``{column: name}``, the verified rate and mean time at its smallest and
    largest value (averaged over the other axes), ours and the paper's; with ``summary``,
    first the counts and the allocation's share of one-pixel cells."""
    lines = _summary(table) if summary else []
    for column, name in axes.items():
        values = sorted(table[column].unique())
        if len(values) < 2:
            continue
        lo, hi = table[table[column] == values[0]], table[table[column] == values[-1]]
        lines.append(
            f"{name} {_fmt(values[0])} → {_fmt(values[-1])}: verified rate "
            f"{_rate(lo.verified_rate)} → {_rate(hi.verified_rate)} (paper "
            f"{_rate(lo.paper_rate)} → {_rate(hi.paper_rate)}); mean time "
            f"{lo.time_mean.mean():.3g} s → {hi.time_mean.mean():.3g} s (paper "
            f"{lo.paper_time_mean.mean():.3g} s → {hi.paper_time_mean.mean():.3g} s)."
        )
    return lines


def _summary(table: pd.DataFrame) -> list[str]:
    lines = []
    total = int(table.instances.sum())
    holds, inside = int(table.holds.sum()), int(table.seeds_inside.sum())
    at_seed = int(table.violated_at_seed.sum())
    lines.append(
        f"{total} instances: {holds} holds, {int(table.violated.sum())} violated "
        f"({at_seed} of them at the seed image itself, λ = 0), {int(table.unknown.sum())} "
        f"unknown"
        + (
            f", {int(table.errors.sum())} not certifiable (stored as errors)"
            if "errors" in table
            else ""
        )
        + f"; {inside} had the seed's target-model pose inside Ξ."
    )
    if "argmax_outside" in table and table.argmax_outside.notna().any():
        lines.append(
            f"Of the sampled hull images of its holds, {table.argmax_outside.mean():.1%} (mean "
            "over cells) have an argmax → PnP pose outside Ξ: what this reading lets through."
        )
    if "dv_zero" in table:
        lines.append(
            f"The allocation gave {table.dv_zero.mean():.0%} of the keypoint coordinates "
            f"δv = 0 (a one-pixel cell) and a mean δv of {table.dv_mean.mean():.2f} heatmap "
            "px: a one-pixel cell holds only if the network's peak is on the rounded "
            "ground-truth pixel, so violations at the seed image itself measure how often "
            "the allocation is tighter than the network's own accuracy."
        )
    if "pb_holds" in table and table.pb_holds.notna().any():
        inside = table.seeds_inside.sum()
        rate = lambda column: "n/a" if not inside else f"{column.sum() / inside:.1%}"  # noqa: E731
        lines.append(
            f"Pose-bound method (reachable keypoint regions → pose decision) on the same "
            f"instances: {int(table.pb_holds.sum())} holds; verified rate "
            f"{rate(table.pb_verified_rate * table.seeds_inside)} against the allocation's "
            f"{rate(table.verified_rate * table.seeds_inside)}. It verifies "
            f"{int(table.pb_only.sum())} instance(s) the allocation method does not, and the "
            f"allocation method {int(table.allocation_only.sum())} it does not. PnP re-solved "
            f"at region corners leaves Ξ for {int(table.pb_nonlinear_outside.sum())} of its "
            "holds (the linearisation's error, shared with the allocation method). Mean time "
            f"{table.pb_time_mean.mean():.3g} s per instance (one region search per hull, "
            "counted in full for each of its α, κ cells)."
        )
    if "pb_by_enumeration" in table and table.pb_by_enumeration.notna().any():
        lines.append(
            f"Decided by a witness image outside Ξ: {int(table.pb_by_witness.sum())}; by PnP on "
            f"every combination of region pixels (exact for argmax → PnP): "
            f"{int(table.pb_by_enumeration.sum())}, {int(table.pb_enumeration_holds.sum())} of "
            f"them holds; by the linearised bound: {int(table.pb_by_linearised.sum())}."
        )
    return lines


_RATE = ("verified_rate", "paper_rate", "Verified rate (allocation method)")


@functools.partial(_per_group, compare=_RATE)
def _local(table):
    return campaign_readings(
        table, {"alpha": "α", "kappa": "κ", "m": "m", "overlapping": "overlapping"}
    )


@functools.partial(_per_group, compare=_RATE)
def _global(table):
    lines = campaign_readings(table, {"alpha": "α", "kappa": "κ"})
    for kind in sorted(table.kind.unique()):
        part = table[table.kind == kind]
        lines += [f"{kind}: " + s for s in campaign_readings(part, {"level": "level"}, False)]
    return lines


@functools.partial(_per_group, compare=_RATE)
def _resnet(table):
    return campaign_readings(table, {"overlapping": "overlapping"})


def _rate(values: pd.Series) -> str:
    values = values.dropna()
    return "n/a" if values.empty else f"{values.mean():.1%}"


def _fmt(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    return f"{value:g}"
