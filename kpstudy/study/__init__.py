"""The study: campaigns of instances, the paper's tables and figures, the report and the
pipeline that makes them all.

:mod:`~kpstudy.study.campaign` (``python -m kpstudy campaign``: grids, the SQLite store,
workers, Dask), :mod:`~kpstudy.study.table_runs` (one verification table from its
campaigns, notebooks 06–08), :mod:`~kpstudy.study.tables`,
:mod:`~kpstudy.study.comparison` and :mod:`~kpstudy.study.trends` (the tables beside the
paper's, figures, the paper's statements), :mod:`~kpstudy.study.heatmaps` (F-sym),
:mod:`~kpstudy.study.allocation_figures` (F-alloc, F-kps), :mod:`~kpstudy.study.report`
(REPORT.md), :mod:`~kpstudy.study.vnncomp` (``python -m kpstudy export-benchmark``: the
instances as a VNN-COMP benchmark) and :mod:`~kpstudy.study.reproduction` (``python -m
kpstudy reproduce``: profiles and stages; docs/design.md §6).

May import: every other subpackage (:mod:`kpstudy.pose`, :mod:`kpstudy.verify`,
:mod:`kpstudy.models`, :mod:`kpstudy.certify`) and the infrastructure; not
:mod:`kpstudy.cli` (docs/design.md §2).
"""

from kpstudy.study.allocation_figures import (
    ALPHAS,
    FRAME_COLUMNS,
    allocation_errorbars,
    allocation_frame,
    inside_fractions,
    keypoint_deviation_samples,
    plot_allocation,
    plot_keypoint_samples,
)
from kpstudy.study.campaign import (
    Instance,
    ResultStore,
    Settings,
    grid,
    provenance,
    run_campaign,
    run_study,
    store_path,
)
from kpstudy.study.comparison import (
    CONDITIONS,
    GRID_COLUMNS,
    PAPER_HARDWARE,
    compact_table,
    method_cells,
    plot_comparison,
    save_comparison,
)
from kpstudy.study.heatmaps import (
    backbone_heatmaps,
    marginal_indicators,
    plot_indicators,
    summarise_indicators,
    symmetry_indicators,
)
from kpstudy.study.report import (
    COMPARED,
    SECTIONS,
    campaign_summary,
    compact_markdown,
    t_prob_readings,
    trend_markdown,
    trend_readings,
    write_report,
)
from kpstudy.study.reproduction import (
    PROFILES,
    STAGES,
    Profile,
    profile,
    reproduce,
)
from kpstudy.study.table_runs import (
    TABLES,
    StudyTable,
    TableKind,
    run_table,
)
from kpstudy.study.tables import (
    PAPER_T_GLOBAL,
    PAPER_T_LOCAL,
    PAPER_T_PROB,
    PAPER_T_RESNET,
    plot_pose_bounds,
    pose_bound_ratios,
    reading_comparison,
    summarise,
    t_global,
    t_local,
    t_prob,
    t_resnet,
)
from kpstudy.study.trends import (
    STATEMENTS,
    Statement,
    Trend,
    describe,
    trend,
    trend_table,
    verdict,
)
from kpstudy.study.vnncomp import (
    DTYPES,
    export_benchmark,
    instance_name,
)

__all__ = [
    "ALPHAS",
    "COMPARED",
    "CONDITIONS",
    "DTYPES",
    "FRAME_COLUMNS",
    "GRID_COLUMNS",
    "PAPER_HARDWARE",
    "PAPER_T_GLOBAL",
    "PAPER_T_LOCAL",
    "PAPER_T_PROB",
    "PAPER_T_RESNET",
    "PROFILES",
    "SECTIONS",
    "STAGES",
    "STATEMENTS",
    "TABLES",
    "Instance",
    "Profile",
    "ResultStore",
    "Settings",
    "Statement",
    "StudyTable",
    "TableKind",
    "Trend",
    "allocation_errorbars",
    "allocation_frame",
    "backbone_heatmaps",
    "campaign_summary",
    "compact_markdown",
    "compact_table",
    "describe",
    "export_benchmark",
    "grid",
    "inside_fractions",
    "instance_name",
    "keypoint_deviation_samples",
    "marginal_indicators",
    "method_cells",
    "plot_allocation",
    "plot_comparison",
    "plot_indicators",
    "plot_keypoint_samples",
    "plot_pose_bounds",
    "pose_bound_ratios",
    "profile",
    "provenance",
    "reading_comparison",
    "reproduce",
    "run_campaign",
    "run_study",
    "run_table",
    "save_comparison",
    "store_path",
    "summarise",
    "summarise_indicators",
    "symmetry_indicators",
    "t_global",
    "t_local",
    "t_prob",
    "t_prob_readings",
    "t_resnet",
    "trend",
    "trend_markdown",
    "trend_readings",
    "trend_table",
    "verdict",
    "write_report",
]
