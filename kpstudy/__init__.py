"""kpstudy: certify heatmap-keypoint + PnP pose estimators against convex hulls of images.

The tree, top-down as the data flows (docs/design.md §2; each part imports only the
parts its row there names, which tests/test_layout.py checks):

- infrastructure: ``kpstudy._checks`` (argument checks), ``kpstudy._memo`` (memo
  keys), ``kpstudy._lazy`` (the subpackages' re-exports), :mod:`kpstudy.io` (atomic
  files, the code fingerprint);
- :mod:`kpstudy.pose`: pose math, no network — geometry and the tolerance box Ξ, PnP,
  the sensitivity ``dξ/dv``, the tolerance allocation, its Monte Carlo check;
- :mod:`kpstudy.verify`: the network-agnostic verifier over convex hulls of images;
- :mod:`kpstudy.models`: backbones, heads, pooling cells and the proxy; preprocessing,
  data, training (certified training on :mod:`kpstudy.verify`'s bounds) and evaluation;
- :mod:`kpstudy.certify`: one seed image's hull → one record, by the paper's allocation
  method or the pose-bound method (reachable keypoint regions → PnP);
- :mod:`kpstudy.study`: campaigns, tables, figures, the report, the VNN-COMP export and
  ``reproduce``'s stages, which the notebooks call;
- ``kpstudy.cli``: ``python -m kpstudy reproduce|train|evaluate|campaign|export-benchmark``.

Each subpackage re-exports its public names (``from kpstudy.certify import certify``).
Conventions are those of docs/design.md §3.
"""

__version__ = "0.1.0"
