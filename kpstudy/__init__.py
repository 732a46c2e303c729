"""kpstudy: certify heatmap-keypoint + PnP pose estimators against convex hulls of images.

Pose-side core (no neural network): :mod:`kpstudy.pose.geometry` (with the tolerance box Ξ),
:mod:`kpstudy.pose.pnp`, :mod:`kpstudy.pose.sensitivity`, :mod:`kpstudy.pose.allocation`,
:mod:`kpstudy.pose.montecarlo`. Networks and the verifier: :mod:`kpstudy.models.preprocess`,
:mod:`kpstudy.models`, :mod:`kpstudy.models.pooling` (the proxy's cells, on
:func:`kpstudy.verify.ops.cell_pool`), :mod:`kpstudy.models.training`, :mod:`kpstudy.verify`,
:mod:`kpstudy.certify.allocation_method`, :mod:`kpstudy.certify.pose_bound_method`. The study:
:mod:`kpstudy.study.campaign`, :mod:`kpstudy.study.tables`, :mod:`kpstudy.study.report`,
:mod:`kpstudy.study.reproduction` and the notebooks. Conventions are those of docs/design.md §3.
"""

__version__ = "0.1.0"
