"""The verifier: sound bounds and branch and bound over convex hulls of images.

An instance is a problem (model, input set, output spec) × a bound method × a search
(docs/design.md §4.6–4.8): :class:`ConvexHull` (exact), :class:`Parallelotope` (the
ModelVerification.jl baseline) or :class:`Box` (ℓ∞); :class:`ArgmaxSpec`;
:func:`output_bounds` with ``'ibp'``, ``'forward'``, ``'crown'`` or ``'zonotope'`` (the
default of :func:`verify`: one shared error symbol per unstable ReLU keeps the bounds of a
trained CNN near the sampled range, where forward bounds grow ~10× per layer);
:func:`verify` returns a :class:`Result` — ``holds``, ``violated`` with a re-checked
counterexample, or ``unknown``; :func:`reachable_argmax` returns sound sets of the indices
each keypoint's argmax can take (:class:`Regions`), with witnesses; :func:`bound_profile`
shows, node by node, how far a method's bounds are from the sampled range;
:func:`export_instance` writes ONNX + VNN-LIB for other verifiers and :func:`export_onnx`
a plain network (a backbone, a proxy).
"""

from kpstudy.verify.bab import verify
from kpstudy.verify.bounds import output_bounds
from kpstudy.verify.export import export_instance, export_onnx, read_vnnlib_polytope
from kpstudy.verify.profile import bound_profile
from kpstudy.verify.reachable import Frontier, Regions, reachable_argmax
from kpstudy.verify.result import Counterexample, Result
from kpstudy.verify.sets import Box, ConvexHull, Parallelotope
from kpstudy.verify.spec import ArgmaxSpec

__all__ = [
    "ArgmaxSpec",
    "Box",
    "ConvexHull",
    "Counterexample",
    "Frontier",
    "Parallelotope",
    "Regions",
    "Result",
    "bound_profile",
    "export_instance",
    "export_onnx",
    "output_bounds",
    "reachable_argmax",
    "read_vnnlib_polytope",
    "verify",
]
