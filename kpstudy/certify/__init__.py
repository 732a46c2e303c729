"""Certification of one seed image's hull of perturbed images: the two methods.

:mod:`~kpstudy.certify.hull` drives a hull (:func:`~kpstudy.certify.hull.certify` for one
cell ``(α, κ)``, :func:`~kpstudy.certify.hull.certify_cells` for a hull's cells together):
per cell, one record from both methods. :mod:`~kpstudy.certify.allocation_method` is the
paper's method on one instance (one seed image → one verification instance → one record):
nominal pose, sensitivity, allocated keypoint tolerances, pooling cells → the proxy and its
spec (:func:`~kpstudy.certify.allocation_method.build_instance`), the verifier over the
exact hull (:func:`~kpstudy.certify.allocation_method.verify_instance`).
:mod:`~kpstudy.certify.pose_bound_method` is the regions → PnP method: where each keypoint's
argmax can go over the hull (:mod:`~kpstudy.certify.pose_bound_regions`), the pose-error
decision rules over those regions (:mod:`~kpstudy.certify.pose_bound_rules`) and the images
whose argmax → PnP pose leaves Ξ (:mod:`~kpstudy.certify.pose_bound_attack`), composed by
:class:`~kpstudy.certify.pose_bound_method.HullPoseBound`
(:func:`~kpstudy.certify.pose_bound_method.pose_bound`; docs/design.md §4.11–4.12).

May import: the infrastructure (``kpstudy._checks``, ``_memo``, ``_lazy``, ``io``),
:mod:`kpstudy.pose`, :mod:`kpstudy.verify` and :mod:`kpstudy.models` (docs/design.md §2).
"""

from kpstudy._lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "hull": None,  # its __all__
        "allocation_method": None,
        "pose_bound_method": None,
        "pose_bound_regions": None,
        "pose_bound_rules": None,
        "pose_bound_attack": None,
    },
)
