"""Pose math, no neural network: the camera and the tolerance box Ξ, PnP, the pose's
sensitivity to the keypoints, the tolerance allocation and its Monte Carlo check.

:mod:`~kpstudy.pose.geometry` (projection, the Euler convention, the pose error, Ξ),
:mod:`~kpstudy.pose.pnp` (OpenCV PnP and a batched LM PnP in torch),
:mod:`~kpstudy.pose.sensitivity` (``dξ/dv`` at the PnP optimum),
:mod:`~kpstudy.pose.allocation` (the exact integer tolerance allocation, a MILP) and
:mod:`~kpstudy.pose.montecarlo` (probabilistic soundness and completeness, T-prob).

May import: the infrastructure (``kpstudy._checks``, ``_memo``, ``_lazy``, ``io``)
only (docs/design.md §2).
"""

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "allocation": None,  # its __all__
        "geometry": (
            "EPS_R",
            "EPS_T",
            "EULER_SEQ",
            "POSE_AXES",
            "euler_from_matrix",
            "euler_from_matrix_torch",
            "inside_tolerance",
            "matrix_from_euler",
            "matrix_from_euler_torch",
            "pose_error",
            "project",
            "project_batch",
            "tolerance",
            "wrap_degrees",
        ),
        "montecarlo": (
            "probabilistic_completeness",
            "probabilistic_soundness",
            "soundness_completeness_table",
        ),
        "pnp": (
            "PnPResult",
            "solve_pnp",
            "solve_pnp_batch",
        ),
        "sensitivity": (
            "pose_sensitivity",
            "reprojection_cost",
        ),
    },
)
