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

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "allocation_figures": (
            "ALPHAS",
            "FRAME_COLUMNS",
            "allocation_errorbars",
            "allocation_frame",
            "allocation_table",
            "inside_fractions",
            "keypoint_deviation_samples",
            "plot_allocation",
            "plot_keypoint_samples",
        ),
        "campaign": (
            "Instance",
            "ResultStore",
            "Settings",
            "grid",
            "provenance",
            "run_campaign",
            "run_study",
            "store_path",
        ),
        "comparison": (
            "CONDITIONS",
            "GRID_COLUMNS",
            "PAPER_HARDWARE",
            "compact_table",
            "method_cells",
            "plot_comparison",
            "save_comparison",
        ),
        "heatmaps": (
            "backbone_heatmaps",
            "marginal_indicators",
            "plot_indicators",
            "summarise_indicators",
            "symmetry_indicators",
        ),
        "report": (
            "COMPARED",
            "SECTIONS",
            "campaign_summary",
            "compact_markdown",
            "t_prob_readings",
            "trend_markdown",
            "trend_readings",
            "write_report",
        ),
        "reproduction": (
            "PROFILES",
            "STAGES",
            "Profile",
            "profile",
            "reproduce",
        ),
        "table_runs": (
            "TABLES",
            "StudyTable",
            "TableKind",
            "run_table",
        ),
        "tables": (
            "PAPER_T_GLOBAL",
            "PAPER_T_LOCAL",
            "PAPER_T_PROB",
            "PAPER_T_RESNET",
            "plot_pose_bounds",
            "pose_bound_ratios",
            "reading_comparison",
            "summarise",
            "t_global",
            "t_local",
            "t_prob",
            "t_resnet",
        ),
        "trends": (
            "STATEMENTS",
            "Statement",
            "Trend",
            "describe",
            "trend",
            "trend_table",
            "verdict",
        ),
        "vnncomp": (
            "DTYPES",
            "export_benchmark",
            "instance_name",
        ),
    },
)
