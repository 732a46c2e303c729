"""The verifier: sound bounds and branch and bound over convex hulls of images.

An instance is a problem (model, input set, output spec) × a bound method × a search
(docs/design.md §4.6–4.8): :class:`~kpstudy.verify.sets.ConvexHull` (exact),
:class:`~kpstudy.verify.sets.Parallelotope` (the ModelVerification.jl baseline) or
:class:`~kpstudy.verify.sets.Box` (ℓ∞); :class:`~kpstudy.verify.spec.ArgmaxSpec`;
:func:`~kpstudy.verify.bounds.output_bounds` with ``'ibp'``, ``'forward'``, ``'crown'`` or
``'zonotope'`` (the default of :func:`~kpstudy.verify.bab.verify`: one shared error symbol
per unstable ReLU keeps the bounds of a trained CNN near the sampled range, where forward
bounds grow ~10× per layer); :func:`~kpstudy.verify.bab.verify` returns a
:class:`~kpstudy.verify.result.Result` — ``holds``, ``violated`` with a re-checked
counterexample, or ``unknown``; :func:`~kpstudy.verify.reachable.reachable_argmax` returns
sound sets of the indices each keypoint's argmax can take
(:class:`~kpstudy.verify.reachable.Regions`), with witnesses;
:func:`~kpstudy.verify.profile.bound_profile` shows, node by node, how far a method's bounds
are from the sampled range; :func:`~kpstudy.verify.export.export_instance` writes ONNX +
VNN-LIB for other verifiers and :func:`~kpstudy.verify.export.export_onnx` a plain network
(a backbone, a proxy).
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
