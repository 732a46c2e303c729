"""kpstudy: certify heatmap-keypoint + PnP pose estimators against convex hulls of images.

Pose-side core (no neural network): :mod:`kpstudy.geometry`, :mod:`kpstudy.pnp`,
:mod:`kpstudy.sensitivity`, :mod:`kpstudy.allocation`, :mod:`kpstudy.pooling`,
:mod:`kpstudy.montecarlo`. Networks and the verifier: :mod:`kpstudy.models`,
:mod:`kpstudy.train`, :mod:`kpstudy.verify`, :mod:`kpstudy.certify`,
:mod:`kpstudy.pose_bound`. The study:
:mod:`kpstudy.campaign`, :mod:`kpstudy.tables`, :mod:`kpstudy.report`,
:mod:`kpstudy.reproduce` and the notebooks. Conventions are those of docs/design.md §3.
"""

__version__ = "0.1.0"
