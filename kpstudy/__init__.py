"""kpstudy: certify heatmap-keypoint + PnP pose estimators against convex hulls of images.

Pose-side core (no neural network): :mod:`kpstudy.geometry`, :mod:`kpstudy.pnp`,
:mod:`kpstudy.sensitivity`, :mod:`kpstudy.allocation`, :mod:`kpstudy.pooling`,
:mod:`kpstudy.montecarlo`. Conventions are those of DESIGN.md §3.
"""

__version__ = "0.1.0"
