"""Certification of one seed image's hull of perturbed images: the two methods.

:mod:`~kpstudy.certify.allocation_method` is the paper's method per instance (one seed
image → one verification instance → one record): nominal pose, sensitivity, allocated
keypoint tolerances, pooling cells → the proxy and its spec, the verifier over the exact
hull (:func:`certify`, :func:`certify_cells` for a hull's (α, κ) cells together,
:func:`build_instance` for the instance alone). :mod:`~kpstudy.certify.pose_bound_method`
is the regions → PnP method: where each keypoint's argmax can go over the hull, and the
pose-error verdict that follows (:func:`pose_bound`, :class:`HullPoseBound`;
docs/design.md §4.11–4.12).

May import: the infrastructure (``kpstudy._checks``, ``_memo``, ``_lazy``, ``io``),
:mod:`kpstudy.pose`, :mod:`kpstudy.verify` and :mod:`kpstudy.models` (docs/design.md §2).
"""

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "allocation_method": None,  # its __all__
        "pose_bound_method": None,  # its __all__
    },
)
