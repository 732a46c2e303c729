"""The study: campaigns of instances, the paper's tables and figures, the report and the
pipeline that makes them all.

:mod:`~kpstudy.study.campaign` (``python -m kpstudy campaign``: grids, the SQLite store,
workers, Dask), :mod:`~kpstudy.study.table_runs` (one verification table from its
campaigns, notebooks 06–08), :mod:`~kpstudy.study.tables`,
:mod:`~kpstudy.study.comparison` and :mod:`~kpstudy.study.trends` (the tables beside the
paper's, figures, the paper's statements), :mod:`~kpstudy.study.heatmaps` (F-sym),
:mod:`~kpstudy.study.allocation_figures` (F-alloc, F-kps), :mod:`~kpstudy.study.report`
(REPORT.md), :mod:`~kpstudy.study.reference` (``python -m kpstudy publish``: a run kept
as the reference result), :mod:`~kpstudy.study.vnncomp` (``python -m kpstudy export-benchmark``: the
instances as a VNN-COMP benchmark) and :mod:`~kpstudy.study.reproduction` (``python -m
kpstudy reproduce``: profiles and stages; docs/design.md §6).

May import: every other subpackage (:mod:`kpstudy.pose`, :mod:`kpstudy.verify`,
:mod:`kpstudy.models`, :mod:`kpstudy.certify`) and the infrastructure; not
``kpstudy.cli`` (docs/design.md §2).
"""

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "allocation_figures": None,  # its __all__
        "campaign": None,  # its __all__
        "comparison": None,  # its __all__
        "heatmaps": (
            "backbone_heatmaps",
            "marginal_indicators",
            "plot_indicators",
            "summarise_indicators",
            "symmetry_indicators",
        ),
        "reference": (
            "RUN_LOG",
            "code_commit",
            "log_stage",
            "notebook_seconds",
            "publish",
            "run_log",
            "stamp_markdown",
        ),
        "report": None,  # its __all__
        "reproduction": (
            "PROFILES",
            "STAGES",
            "Profile",
            "compare_results",
            "profile",
            "reproduce",
        ),
        "table_runs": None,  # its __all__
        "tables": None,  # its __all__
        "trends": None,  # its __all__
        "vnncomp": None,  # its __all__
    },
)
