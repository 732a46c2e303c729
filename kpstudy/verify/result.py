"""What a verification run returns: holds / violated (with a counterexample) / unknown."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class Counterexample:
    """A point of the input set on which the concrete model breaks the spec.

    Attributes
    ----------
    point : Tensor
        The set's parameter: ``λ (n,)`` for a hull or parallelotope, the image for a box.
    image : Tensor, shape S
        The model input, in the model's dtype.
    group : int
        A violated group (keypoint).
    margin : float
        That group's smallest margin ``y[t] − y[j]`` on ``image`` (<= 0).
    """

    point: torch.Tensor
    image: torch.Tensor
    group: int
    margin: float


@dataclass
class Result:
    """Outcome of :func:`kpstudy.verify.verify`.

    Attributes
    ----------
    status : str
        ``'holds'`` (proved for every point of the set), ``'violated'`` (a counterexample,
        re-checked on the concrete model) or ``'unknown'`` (budget spent).
    group_status : list of str
        Per group: ``'holds'``, ``'violated'``, ``'unknown'`` or ``'excluded'`` (no target).
    counterexample : Counterexample or None
    time : float
        Seconds.
    nodes : int
        Branch-and-bound nodes bounded.
    stats : dict
        Bound statistics: the method, root lower margin per group, depth, float64 rechecks.
    """

    status: str
    group_status: list[str]
    counterexample: Counterexample | None
    time: float
    nodes: int
    stats: dict = field(default_factory=dict)
