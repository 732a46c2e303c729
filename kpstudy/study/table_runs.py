"""One verification table of the study from its campaigns: the records, the table beside
the paper's, its figures and files (T-local, T-global, T-resnet: notebooks 06–08).

:func:`run_table` is what each of those notebooks calls: the campaigns of every model ×
tolerance reading × perturbation kind of the table (:func:`kpstudy.study.campaign.run_study`,
resumable stores under ``out/campaigns``), then ``out/tables/<name>_records.csv``, the
table ``out/tables/<name>.csv`` / ``.md`` (:mod:`kpstudy.study.tables`), the figure beside the
paper's ``out/figures/<name>.png`` (:func:`kpstudy.study.comparison.plot_comparison`) and,
where the pose-bound method ran, ``out/figures/<name>_pose_bound.png``
(:func:`kpstudy.study.tables.plot_pose_bounds`). The report (:mod:`kpstudy.study.report`) reads
those files.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from kpstudy import _checks
from kpstudy.io import save_figure, write_table, write_text_atomic
from kpstudy.study import campaign, comparison, tables

__all__ = ["TABLES", "StudyTable", "TableKind", "run_table"]


@dataclass(frozen=True)
class TableKind:
    """What one of the study's verification tables runs and how it is summarised."""

    kinds: tuple[str, ...]  # perturbation kinds (kpstudy.study.campaign.grid)
    summarise: Callable[[pd.DataFrame], pd.DataFrame]  # records → the table
    title: str  # the figures' title


#: The study's verification tables (paper §8.4), by the name of their files.
TABLES = {
    "t_local": TableKind(("objects",), tables.t_local, "T-local: object occlusions"),
    "t_global": TableKind(
        ("contrast", "brightness"), tables.t_global, "T-global: brightness and contrast"
    ),
    "t_resnet": TableKind(("blocks",), tables.t_resnet, "T-resnet: block occlusions (ResNet-18)"),
}


@dataclass
class StudyTable:
    """What :func:`run_table` made.

    Attributes
    ----------
    records : DataFrame
        One row per instance, model and tolerance reading (campaign records).
    table : DataFrame
        The summary per cell, the paper's numbers beside ours.
    readings : list of str
        Per model, which tolerance reading matches the paper's verified rate
        (:func:`kpstudy.study.tables.reading_comparison`).
    figures : dict of str → Path
        The PNGs written: ``'comparison'`` and, where the pose-bound method ran,
        ``'pose_bound'``.
    """

    records: pd.DataFrame
    table: pd.DataFrame
    readings: list[str] = field(default_factory=list)
    figures: dict[str, Path] = field(default_factory=dict)


def run_table(
    name: str,
    checkpoints: dict[str, str],
    data_dir,
    out,
    *,
    grid_options: dict,
    tolerance_units: Iterable[str] = ("heatmap",),
    pose_bound: dict[str, dict] | None = None,
    **campaign_options,
) -> StudyTable:
    """Run (or resume) one verification table and write its files under ``out``.

    Parameters
    ----------
    name : {'t_local', 't_global', 't_resnet'}
        The table (:data:`TABLES`).
    checkpoints : dict
        ``{model name: checkpoint path}``, e.g. ``{"cnn": …, "cnn_patch_smooth": …}``.
    data_dir : path
        The dataset with its perturbation sets.
    out : path
        The run's folder: ``campaigns/``, ``tables/`` and ``figures/`` go under it.
    grid_options, tolerance_units, pose_bound, **campaign_options :
        :func:`kpstudy.study.campaign.run_study`'s (``alphas``, ``kappas``, ``seeds``, ``ms`` of
        the grid; the readings; the pose-bound method's settings per model; ``timeout``,
        ``nodes``, ``method``, ``workers``, ``scheduler``, …).

    Returns
    -------
    StudyTable
    """
    _checks.choice(name, "name", sorted(TABLES))
    kind, out = TABLES[name], Path(out)
    records = campaign.run_study(
        checkpoints,
        data_dir,
        kind.kinds,
        out / "campaigns",
        grid_options=grid_options,
        tolerance_units=tolerance_units,
        pose_bound=pose_bound,
        **campaign_options,
    )
    write_text_atomic(out / "tables" / f"{name}_records.csv", records.to_csv(index=False))
    table = kind.summarise(records)
    write_table(table, out / "tables" / name)
    readings = []
    for model, part in table.groupby("model"):
        sentence = tables.reading_comparison(part, "verified_rate", "paper_rate", "Verified rate")
        if sentence:
            readings.append(f"{model}: {sentence}")
    figures = {
        "comparison": save_figure(
            comparison.plot_comparison(table, kind.title), out / "figures" / f"{name}.png"
        )
    }
    if "pb_status" in records and records["pb_status"].notna().any():
        figure = tables.plot_pose_bounds(records, f"{kind.title}: pose-error bounds")
        figures["pose_bound"] = save_figure(figure, out / "figures" / f"{name}_pose_bound.png")
    return StudyTable(records, table, readings, figures)
