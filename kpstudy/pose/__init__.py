"""Pose math, no neural network: the camera and the tolerance box Ξ, PnP, the pose's
sensitivity to the keypoints, the tolerance allocation and its Monte Carlo check.

:mod:`~kpstudy.pose.geometry` (projection, the Euler convention, the pose error, Ξ),
:mod:`~kpstudy.pose.pnp` (OpenCV PnP and a batched LM PnP in torch),
:mod:`~kpstudy.pose.sensitivity` (``dξ/dv`` at the PnP optimum),
:mod:`~kpstudy.pose.allocation` (the exact integer tolerance allocation, a MILP) and
:mod:`~kpstudy.pose.montecarlo` (probabilistic soundness and completeness, T-prob).

May import: the infrastructure (``kpstudy._checks``, ``kpstudy._memo``, ``kpstudy.io``)
only (docs/design.md §2).
"""

from kpstudy.pose.allocation import (
    MAX_BOUND,
    TOLERANCE_UNITS,
    Allocation,
    allocate_many,
    allocate_tolerances,
    allocation_scale,
)
from kpstudy.pose.geometry import (
    EPS_R,
    EPS_T,
    EULER_SEQ,
    POSE_AXES,
    euler_from_matrix,
    euler_from_matrix_torch,
    inside_tolerance,
    matrix_from_euler,
    matrix_from_euler_torch,
    pose_error,
    project,
    project_batch,
    tolerance,
    wrap_degrees,
)
from kpstudy.pose.montecarlo import (
    probabilistic_completeness,
    probabilistic_soundness,
    soundness_completeness_table,
)
from kpstudy.pose.pnp import PnPResult, solve_pnp, solve_pnp_batch
from kpstudy.pose.sensitivity import pose_sensitivity, reprojection_cost

__all__ = [
    "EPS_R",
    "EPS_T",
    "EULER_SEQ",
    "MAX_BOUND",
    "POSE_AXES",
    "TOLERANCE_UNITS",
    "Allocation",
    "PnPResult",
    "allocate_many",
    "allocate_tolerances",
    "allocation_scale",
    "euler_from_matrix",
    "euler_from_matrix_torch",
    "inside_tolerance",
    "matrix_from_euler",
    "matrix_from_euler_torch",
    "pose_error",
    "pose_sensitivity",
    "probabilistic_completeness",
    "probabilistic_soundness",
    "project",
    "project_batch",
    "reprojection_cost",
    "solve_pnp",
    "solve_pnp_batch",
    "soundness_completeness_table",
    "tolerance",
    "wrap_degrees",
]
