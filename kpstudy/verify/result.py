"""What a verification run returns: holds / violated (with a counterexample) / unknown."""

from __future__ import annotations

import math
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
        That group's smallest margin ``y[t] − y[j]`` (<= 0) at the set's exact point: the
        model in float64 on the image computed in float64 (for a float32 model and set,
        not ``image``, which is that point rounded to float32).
    """

    point: torch.Tensor
    image: torch.Tensor
    group: int
    margin: float


@dataclass
class Result:
    """Outcome of :func:`kpstudy.verify.bab.verify`.

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
        Search statistics: the method, depth, node batch, whether the budget ran out
        (``timed_out``) and what ended the search early (``stopped``: ``'nodes'``,
        ``'time'``, ``'stop'`` at a counterexample, or None), float64 rechecks, and per
        group two ends of its smallest margin over the set:
        ``root_margin``, the root node's lower bound (None if no node was bounded), and
        ``attack_margin``, the smallest margin the concrete model showed at the points
        tried (vertices, centroids, gradient descent), an upper bound. For an
        ``'unknown'`` group the true minimum lies between the two.
    """

    status: str
    group_status: list[str]
    counterexample: Counterexample | None
    time: float
    nodes: int
    stats: dict = field(default_factory=dict)

    def margin_bracket(self) -> tuple[float | None, float | None]:
        """The worst keypoint's smallest margin over the set, bracketed: (the root
        node's lower bound, the smallest margin the attacks found). The lower end is
        ``None`` when some keypoint was not bounded at the root (no node bounded, or a
        counterexample found first)."""
        tried = self.stats.get("attack_margin") or []
        active = [g for g, a in enumerate(tried) if math.isfinite(a)]  # groups with rows
        upper = min((tried[g] for g in active), default=None)
        root = self.stats.get("root_margin")
        lows = [root[g] for g in active] if root is not None else []
        lower = min(lows) if lows and all(math.isfinite(v) for v in lows) else None
        return lower, upper
