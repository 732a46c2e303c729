"""A certified pose-error decision per seed image, from where each keypoint can go.

The paper allocates keypoint tolerances *before* verification and asks the verifier to
keep each keypoint in its cell; this module asks the verifier *where* each keypoint can
go and decides the pose error from that (docs/design.md §4.11). Its parts:
:mod:`~kpstudy.certify.pose_bound_regions` (where each keypoint's argmax can go),
:mod:`~kpstudy.certify.pose_bound_rules` (PnP and the linearised bound over those
regions) and :mod:`~kpstudy.certify.pose_bound_attack` (images whose argmax → PnP pose
leaves Ξ); :class:`HullPoseBound` composes them on one hull, for any number of
tolerance boxes Ξ (half-widths ``eps``, 6: degrees then metres). The steps:

1. :func:`kpstudy.verify.reachable.reachable_argmax` on the backbone's heatmaps (``stride`` 1: the
   argmax head's own pixels; an odd ``stride`` > 1 pools ``stride × stride`` cells around
   the rounded ground truth, like the paper's proxy) gives each keypoint's possible pixels,
   a sound superset of the argmax pixels over the hull;
2. each possible pixel is a keypoint position in image pixels (a deviation
   ``δ = v − v_gt`` from the ground truth);
3. the *linearised* pose error ``δξ = M δ`` (``M = dξ/dv`` in image pixels) is bounded per
   axis by ``max |Σ_k M_k δ_k|`` over the product of the keypoints' pixel sets, which is
   exact for that product *of the linearisation* and separable per keypoint
   (:func:`~kpstudy.certify.pose_bound_rules.linearised_bound`); it is never above the
   triangle-inequality bound ``Σ_j |M_ij| max |δ_j|``, but it is not a bound on PnP's
   error;
4. where the product of the region sizes is at most :data:`MAX_COMBINATIONS`, PnP is
   solved on *every* combination of region pixels
   (:func:`~kpstudy.certify.pose_bound_rules.enumerated_pose_error`, in chunks of
   :data:`~kpstudy.certify.pose_bound_rules.ENUMERATION_CHUNK` problems): its per-axis
   maximum is exact for the argmax → PnP pipeline over the product of the regions, hence
   an upper bound over the hull;
5. PnP is re-solved at the extreme and at random combinations of region pixels (the
   nonlinear check, ``pb_nonlinear``: how far the linearisation is off; not for a
   ``violated`` verdict);
6. the argmax → PnP pose is computed at the seed and the hull's vertices first, then at
   random images (one outside Ξ is a real counterexample, and then no node is bounded),
   and at every witness image of the reachability search.

Every PnP here is Levenberg–Marquardt from the nominal pose
(:func:`kpstudy.pose.pnp.solve_pnp_batch`), and a pose that PnP flags as not valid (e.g.
behind the camera, :class:`kpstudy.pose.pnp.PnPResult`) counts as outside Ξ (an ``inf`` error).

Verdict, the first rule that applies deciding (``pb_rule``):

* ``'witness'``: a witness image's argmax pose lies outside Ξ → ``violated``;
* ``'enumeration'`` (the product of the region sizes is ≤ :data:`MAX_COMBINATIONS`):
  ``holds`` when every combination's pose lies in Ξ (``error ≤ ε`` on every axis: the
  decision is exact, so κ, the linearisation's margin, does not scale it), else
  ``unknown`` (a combination outside Ξ that no witness reaches: the regions are
  per-keypoint supersets, so it may not be a real image's). The linearised bound never
  overrules it. A combination that a witness image reaches is decided by ``'witness'``
  before (the witness's argmax pixels lie in the regions);
* ``'linearised'`` (more combinations): ``holds`` when ``κ · bound ≤ ε`` on every axis,
  else ``unknown``. Such a ``holds`` covers the argmax head and the *linearised* PnP only.

Before an enumerated ``unknown``,
:func:`~kpstudy.certify.pose_bound_attack.targeted_witness` looks for an image whose
argmax is the combination farthest outside Ξ or one of the ``TARGETED_MOVES``
possible one-keypoint moves that alone leave Ξ
(:func:`~kpstudy.certify.pose_bound_rules.single_moves`); found, and its pose re-checked
in float64 like every witness's, the instance is ``violated`` by ``'witness'``.
An ``unknown`` may then get a second, focused search (:class:`HullPoseBound`'s
``refine_nodes``) and the rules run again on its smaller regions.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from kpstudy import _checks
from kpstudy._memo import digest
from kpstudy.certify.pose_bound_attack import HullArgmaxPoses, targeted_witness
from kpstudy.certify.pose_bound_regions import (
    focus_cells,
    pixel_grid,
    region_pooling,
    search_regions,
    unsearched_regions,
)
from kpstudy.certify.pose_bound_rules import (
    enumerate_combinations,
    linearised_bound,
    pnp_pose_errors,
    single_moves,
)
from kpstudy.models.heads import argmax_keypoints
from kpstudy.models.preprocess import scale_factors, to_image_pixels, to_input_pixels
from kpstudy.pose.geometry import inside_tolerance
from kpstudy.verify.reachable import MAX_START_DEPTH, check_search

__all__ = [
    "FOCUS_PER_NODE",
    "HullPoseBound",
    "MAX_COMBINATIONS",
    "PoseBoundOptions",
    "pose_bound",
]

#: Starting points of :func:`targeted_witness` (the seed and the search's first witnesses).
TARGETED_STARTS = 4
#: One-keypoint moves outside Ξ (:func:`single_moves`, farthest first) that
#: :func:`pose_bound` seeks with :func:`targeted_witness` before ``'unknown'``.
TARGETED_MOVES = 4
#: Most focus cells per node of the second search (:class:`HullPoseBound`'s
#: ``refine_nodes``): a larger focus is not searched. The quick T-local hulls that such a
#: search decided cleared 168 cells in 12 nodes and 21 pixels in 20; on one it could not
#: decide, 6.3·10³ of 6.7·10³ single moves outside Ξ were left after 48.
FOCUS_PER_NODE = 8
#: Most combinations of region pixels (the product of the keypoints' region sizes) that
#: :func:`pose_bound` enumerates with PnP; above it the linearised bound decides.
#: Batched PnP solves about 1.4·10⁵ problems per second on 2 CPU cores.
MAX_COMBINATIONS = 10**6


@dataclass(frozen=True)
class PoseBoundOptions:
    """The pose-bound method's options, :class:`HullPoseBound`'s keywords of the same names
    and defaults, checked when made: a ``ValueError`` names the first that is not valid.
    The one check of these options, whoever takes them (:class:`HullPoseBound`,
    :func:`kpstudy.certify.hull.certify_cells`, the study's settings and profiles).

    ``method``, ``timeout``, ``max_nodes`` and ``start_depth`` follow
    :func:`kpstudy.verify.reachable.reachable_argmax` (a node budget of 0 bounds no node: witnesses
    only); ``start_splits`` is a number in ``[0, MAX_START_DEPTH]``, ``refine_nodes`` an
    integer >= 0 and ``stride`` an odd integer >= 1.
    """

    method: str = "forward"
    timeout: float = 10.0
    max_nodes: int | None = None
    start_depth: int = 0
    start_splits: float = 0.0
    refine_nodes: int = 0
    stride: int = 1

    def __post_init__(self) -> None:
        if _checks.integer(self.stride, "stride", minimum=1) % 2 == 0:
            raise ValueError(f"stride: expected an odd integer >= 1, got {self.stride!r}")
        check_search(self.method, self.timeout, self.max_nodes, self.start_depth)
        splits = self.start_splits
        if isinstance(splits, bool) or not (
            isinstance(splits, int | float) and 0 <= splits <= MAX_START_DEPTH
        ):
            raise ValueError(
                f"start_splits: expected a number in [0, {MAX_START_DEPTH}], got {splits!r}"
            )
        _checks.integer(self.refine_nodes, "refine_nodes", minimum=0)


def pose_bound(backbone, hull, seed, R, t, M, eps, *, kappa: float = 1.0, **search) -> dict:
    """Certify the argmax → PnP pose error of every image of ``hull`` (one seed image):
    ``HullPoseBound(backbone, hull, seed, R, t, M, **search).decide(eps, kappa)``.

    Parameters
    ----------
    backbone, hull, seed, R, t, M, **search :
        As :class:`HullPoseBound` takes them.
    eps, kappa :
        As :meth:`HullPoseBound.decide` takes them.

    Returns
    -------
    dict
        :meth:`HullPoseBound.decide`'s record.
    """
    return HullPoseBound(backbone, hull, seed, R, t, M, **search).decide(eps, kappa)


class HullPoseBound:
    """The pose-bound method on one hull, for any number of tolerance boxes.

    What depends on the hull only is made once, when a cell first needs it, and shared by
    every :meth:`decide` (a campaign's α, κ cells of one hull): the argmax poses of the
    seed, the vertices and random images, the region search, the enumeration of region
    pixels, the float64 model and the targeted attacks (the argmax poses and the float64
    model are ``poses``, a ``kpstudy.certify.pose_bound_attack.HullArgmaxPoses``).

    Parameters
    ----------
    backbone : nn.Module
        Heatmap backbone with ``heatmap_size`` and ``input_size``.
    hull : kpstudy.verify.ConvexHull
        Model inputs ``(n+1, 3, s, s)``, the seed first.
    seed : kpstudy.certify.allocation_method.SeedImage
    R, t : ndarray, shapes (3, 3) and (3,)
        Nominal pose (PnP on the ground truth; t in metres): every PnP here starts there
        and its error is measured from it.
    M : ndarray, shape (6, 2K)
        ``dξ/dv`` at that pose, degrees and metres per *image* pixel (columns
        ``u1, v1, u2, …``); only the linearised bound uses it.
    stride : int
        Odd cell side in heatmap pixels; 1 certifies the argmax pixel itself.
    timeout : float
        Seconds for :func:`kpstudy.verify.reachable.reachable_argmax`.
    method : {'forward', 'zonotope', 'ibp'}
        Its bounds: ``'zonotope'`` gives far smaller regions on a trained CNN, at tens
        of seconds per node on 2 CPU cores (``'forward'``: a fraction of a second).
    max_nodes : int, optional
        Most branch-and-bound nodes of the search: a budget that gives the same regions on
        any machine (``timeout`` then only caps a slow one, and ``pb_stopped`` says which
        fired: ``'time'`` if the cap ended any of the searches, refinements included); 0
        bounds no node (the witnesses alone).
    start_depth : int
        Splits of the hull before the first bounds
        (:func:`kpstudy.verify.reachable.reachable_argmax`).
    start_splits : float
        More splits before the first bounds per perturbed image of the hull: the search
        starts at depth ``start_depth + ⌈start_splits · n⌉`` (at most
        ``kpstudy.verify.reachable.MAX_START_DEPTH``), nodes of about
        ``2^−start_splits`` of the hull per direction whatever its ``n``.
    refine_nodes : int
        Nodes for focused second searches where the verdict is ``unknown`` (0: none).
        Each goes on from where the search so far stopped (same method and timeout) and
        splits only the nodes that keep an unreached cell holding an involved pixel: one
        in a combination outside Ξ under the enumeration rule, one that alone takes the
        pose outside Ξ under the linearised rule (``_refine_focus()``); the rules then
        run again on the smaller regions, and a verdict still ``unknown`` gets another
        round while nodes are left.
    random_corners : int
        Random combinations of region pixels re-solved in the nonlinear check, besides the
        12 extreme ones.
    sample_seed : int

    The method's keywords are checked by :class:`PoseBoundOptions` before any work.
    """

    def __init__(
        self,
        backbone,
        hull,
        seed,
        R,
        t,
        M,
        *,
        stride: int = 1,
        timeout: float = 10.0,
        method: str = "forward",
        max_nodes: int | None = None,
        start_depth: int = 0,
        start_splits: float = 0.0,
        refine_nodes: int = 0,
        random_corners: int = 64,
        sample_seed: int = 0,
    ) -> None:
        PoseBoundOptions(
            method, timeout, max_nodes, start_depth, start_splits, refine_nodes, stride
        )
        start_depth = min(MAX_START_DEPTH, start_depth + math.ceil(start_splits * hull.n))
        self.backbone, self.hull, self.seed, self.R, self.t = backbone, hull, seed, R, t
        self.M, self.stride, self.method = M, stride, method
        self.random_corners, self.sample_seed = random_corners, sample_seed
        self.search = dict(
            method=method, timeout=timeout, max_nodes=max_nodes, start_depth=start_depth
        )
        self.refine = refine_nodes
        hm = backbone.heatmap_size
        self.factors = scale_factors(seed.image_size, hm)
        self.V = np.asarray(seed.keypoints, dtype=np.float64)
        centers = np.rint(to_input_pixels(self.V, self.factors))
        self.centers = np.clip(centers, 0, hm - 1).astype(np.int64)
        self.pooling = region_pooling(self.centers, self.stride, hm)
        self.poses = HullArgmaxPoses(backbone, hull, seed, R, t)  # each λ's made once
        self._made: dict = {}  # shared step → (value, seconds)

    def decide(self, eps, kappa: float = 1.0) -> dict:
        """The verdict and record for Ξ of half-widths ``eps``.

        Parameters
        ----------
        eps : ndarray, shape (6,)
            Ξ's half-widths, degrees then metres.
        kappa : float
            The linearisation's safety margin: where the regions have more than
            :data:`MAX_COMBINATIONS` combinations, ``holds`` needs ``κ · bound ≤ ε`` on
            every axis. The enumerated error is exact and needs ``error ≤ ε`` whatever κ.

        Returns
        -------
        dict
            ``pb_status`` (``'holds'``, ``'violated'`` or ``'unknown'``) and ``pb_rule``,
            the rule that decided it (``'witness'``, ``'enumeration'`` or
            ``'linearised'``: module docstring); ``pb_seed_inside`` (the argmax → PnP pose
            of the seed image lies in Ξ: the pipeline this method certifies is right at
            the seed); ``pb_bound`` (6: the linearised bound ``max |M δ|``, degrees then
            metres; None when a witness decided before any node was bounded: there are no
            regions); ``pb_combinations`` (the product of the region sizes: an int, a float
            above 2⁵³); ``pb_exact`` (6: the largest PnP pose error over every
            combination, degrees then metres, ``inf`` if some pose is not valid) when they
            were enumerated, else None; ``pb_nonlinear`` (6: the largest PnP pose error
            found at region corners; ``inf`` if PnP flags a corner's pose as not valid;
            None for a ``violated`` verdict, which does not use it);
            ``pb_time`` (s; the shared steps this cell used, the search, the enumeration
            and the attack, each counted in full, as if it ran alone); ``pb_nodes``
            (with the refinement's); ``pb_refined`` (the refinement's nodes, 0 if none);
            ``pb_stopped`` (what ended the search early: ``'time'`` when the time cap
            ended the first search or any focused round whose regions this verdict used,
            else what ended the last of them, ``'nodes'`` or None; ``'witness'`` when the
            seed, a vertex or a random image of the hull was already a counterexample and
            no node was bounded); ``pb_complete``
            (possible = reached); ``pb_pixels`` (possible pixels per keypoint);
            ``pb_counterexample`` (λ of the witness image, or None); ``pb_stride``;
            ``pb_method``.
        """
        start, self._spent = time.perf_counter(), 0.0
        eps = np.asarray(eps, dtype=np.float64)
        seed_lam = torch.zeros(1, self.hull.n, dtype=torch.float64)
        seed_inside = bool(inside_tolerance(self.poses.errors(seed_lam)[0], eps).all())
        # Witnesses first: the seed, the hull's corners and random images. One whose argmax
        # pose leaves Ξ decides 'violated', and the search is skipped (its regions: all).
        first = _first_points(self.hull, self.sample_seed)
        corners = 1 + self.hull.n  # the seed and the other vertices, then random images
        early = self.poses.first_outside(eps, first[:corners])
        if early is None:
            early = self.poses.first_outside(eps, first[corners:])
        skipped = early is not None
        if skipped:
            hm = self.backbone.heatmap_size
            regions, pixels = unsearched_regions(hm), [pixel_grid(hm)] * len(self.V)
        else:
            regions, pixels = self._shared("search", lambda: self._search(first))
        verdict = self._judge(eps, kappa, regions, pixels, early)
        # A time cap that ended any search this cell's regions came from (the first or a
        # focused round, shared or not) is recorded, whatever stopped the last one.
        capped = regions.stats["stopped"] == "time"
        refined = 0  # second-search nodes; each round aims at what the last one left
        while verdict["status"] == "unknown" and refined < self.refine:
            budget = self.refine - refined
            focus = self._refine_focus(eps, verdict, regions, pixels, budget)
            if focus is None:
                break
            key = ("refine", budget, digest(*regions.possible, *focus))
            regions, pixels = self._shared(
                key, functools.partial(self._refined, regions, focus, budget)
            )
            refined += regions.nodes - verdict["nodes"]
            capped |= regions.stats["stopped"] == "time"
            verdict = self._judge(eps, kappa, regions, pixels, None)
        stopped = "witness" if skipped else "time" if capped else regions.stats["stopped"]
        return {
            "pb_status": verdict["status"],
            "pb_rule": verdict["rule"],
            "pb_seed_inside": seed_inside,
            "pb_bound": _listed(verdict["bound"]),
            "pb_combinations": verdict["combinations"],
            "pb_exact": _listed(verdict["exact"]),
            "pb_nonlinear": _listed(verdict["nonlinear"]),
            "pb_time": self._spent + time.perf_counter() - start,
            "pb_nodes": regions.nodes,
            "pb_refined": refined,
            "pb_stopped": stopped,
            "pb_complete": regions.complete,
            "pb_pixels": [len(p) for p in pixels],
            "pb_counterexample": verdict["counterexample"],
            "pb_stride": self.stride,
            "pb_method": self.method,
        }

    def _judge(self, eps, kappa, regions, pixels, early) -> dict:
        """The verdict on Ξ (``eps``) from the regions' ``pixels``: ``status``, ``rule``,
        ``counterexample``, ``bound``, ``combinations``, ``exact``, ``nonlinear``,
        ``involved`` (per keypoint, its pixels in a combination outside Ξ, when
        enumerated) and ``nodes`` (the regions'). ``early``: a witness λ found before the
        search, which was then skipped (``regions`` are everywhere: no bound)."""
        seed, R, t = self.seed, self.R, self.t
        positions = [to_image_pixels(p, self.factors) for p in pixels]  # (n_k, 2) image px
        deviations = [p - v for p, v in zip(positions, self.V)]
        combinations = math.prod(len(p) for p in positions)
        verdict = dict(
            combinations=combinations if combinations <= 2**53 else float(combinations),
            bound=None,
            exact=None,
            nonlinear=None,
            involved=None,
            nodes=regions.nodes,
        )
        # Witnesses are real images: their argmax pose decides 'violated'.
        if early is None:
            points = [lam for w in regions.witnesses for lam in w.values()]
            found = self.poses.first_outside(eps, points)
            verdict["bound"], extremes = linearised_bound(self.M, deviations)
        else:
            found = early
        if found is not None:
            return dict(verdict, status="violated", rule="witness", counterexample=found)

        # Nonlinear check: PnP at the extreme and at random combinations of region pixels.
        rng = np.random.default_rng(self.sample_seed)
        random = np.stack([rng.integers(0, len(d), self.random_corners) for d in deviations], 1)
        picks = np.concatenate([extremes, random.reshape(-1, len(deviations))])
        V_corner = np.stack(
            [self.V + np.stack([d[i] for d, i in zip(deviations, row)]) for row in picks]
        )
        verdict["nonlinear"] = pnp_pose_errors(seed, V_corner, R, t).max(0)
        if combinations <= MAX_COMBINATIONS:
            # Exact over the product of the regions; a combination outside Ξ keeps it
            # open, whatever the linearised bound says.
            exact, farthest, involved = self._shared(
                ("enumeration", eps.tobytes(), digest(*pixels)),
                lambda: enumerate_combinations(seed, positions, R, t, eps),
            )
            verdict.update(exact=exact, involved=involved)
            inside = inside_tolerance(exact, eps)  # exact: κ is the linearisation's margin
            rule = "enumeration"
        else:
            inside = inside_tolerance(kappa * verdict["bound"], eps)
            rule = "linearised"
        status, counterexample = ("holds" if inside else "unknown"), None
        if status == "unknown" and rule == "enumeration":
            counterexample = self._attack(eps, regions, pixels, farthest)
            if counterexample is not None:
                status, rule = "violated", "witness"
        return dict(verdict, status=status, rule=rule, counterexample=counterexample)

    def _refine_focus(self, eps, verdict, regions, pixels, budget: int) -> list | None:
        """Per keypoint, the cells an ``unknown`` verdict's second search aims at
        (:func:`~kpstudy.certify.pose_bound_regions.focus_cells`: possible, unreached,
        holding an involved pixel), or None where there are none or more than
        :data:`FOCUS_PER_NODE` per node of ``budget``.

        A pixel is involved, under the enumeration rule, when it takes part in a
        combination outside Ξ; under the linearised rule, when it alone takes the pose
        outside Ξ, the other keypoints at the seed image's argmax (:func:`single_moves`).
        """
        if verdict["rule"] == "enumeration":
            involved = verdict["involved"]
        else:
            base = self._seed_argmax()
            involved = [np.zeros(len(p), dtype=bool) for p in pixels]
            moves = single_moves(self.seed, pixels, base, self.factors, self.R, self.t, eps)
            for k, pixel in moves:
                involved[k] |= (pixels[k] == pixel).all(1)
        focus = focus_cells(regions, self.pooling, self.backbone.heatmap_size, involved)
        cells = sum(len(f) for f in focus)
        return focus if 0 < cells <= FOCUS_PER_NODE * budget else None

    def _refined(self, regions, focus, budget: int) -> tuple:
        """The regions after ``regions``' search goes on for ``budget`` nodes from where
        it stopped (its :class:`~kpstudy.verify.reachable.Frontier`), splitting only where
        a pixel of ``focus`` (per keypoint, cell indices) has no witness yet. Returns the
        :class:`Regions` (their ``nodes`` and ``time`` those of both searches) and their
        pixels."""
        search = dict(self.search, max_nodes=budget)
        second, pixels = search_regions(
            self.backbone, self.hull, self.centers, self.stride, search, focus, regions
        )
        second.nodes += regions.nodes
        second.time += regions.time
        return second, pixels

    def _shared(self, key, make):
        """``make()``'s value, made once per hull; ``decide``'s ``pb_time`` counts its
        seconds in full whether it was made now or before."""
        begin = time.perf_counter()
        if key not in self._made:
            self._made[key] = (make(), time.perf_counter() - begin)
        value, seconds = self._made[key]
        self._spent += seconds - (time.perf_counter() - begin)
        return value

    def _attack(self, eps, regions, pixels, farthest) -> list | None:
        """Can an image reach a combination outside Ξ? :func:`targeted_witness` on the
        farthest combination and the farthest one-keypoint moves; λ of an image found
        whose pose, re-checked, leaves Ξ, else None.

        Over more combinations than are enumerated the regions are the bounds' looseness:
        attacks on them found nothing on the quick T-local hulls and cost more than the
        search, so only enumerated regions are attacked."""
        base = self._seed_argmax()
        targets = [np.stack([p[i] for p, i in zip(pixels, farthest)])]
        moves = single_moves(self.seed, pixels, base, self.factors, self.R, self.t, eps)
        for k, pixel in moves[:TARGETED_MOVES]:
            target = np.full_like(base, -1.0)
            target[k] = pixel
            targets.append(target)
        seen = [lam for w in regions.witnesses for lam in w.values()]
        starts = [torch.zeros(self.hull.n, dtype=torch.float64), *seen[: TARGETED_STARTS - 1]]
        targets = np.rint(targets).astype(np.int64)
        lam = self._shared(
            ("attack", digest(targets, *starts)),
            lambda: targeted_witness(self.backbone, self.hull, targets, starts),
        )
        return None if lam is None else self.poses.first_outside(eps, [lam])

    def _seed_argmax(self) -> np.ndarray:
        """The seed image's argmax pixels ``(K, 2)``, heatmap ``(u, v)``, made once per
        hull."""

        def make():
            seed_lam = torch.zeros(1, self.hull.n, dtype=torch.float64)
            with torch.no_grad():
                heatmaps = self.backbone(self.hull.image(seed_lam))
            return argmax_keypoints(heatmaps)[0].double().numpy()

        return self._shared("seed argmax", make)

    def _search(self, first) -> tuple:
        """The region search. At stride 1 its witnesses start from the argmax pixels at
        ``first`` (λ, evaluated by ``poses``), the random images first and then
        the corners, as the search would take them itself: no image is evaluated twice."""
        if self.stride != 1:
            return search_regions(self.backbone, self.hull, self.centers, self.stride, self.search)
        order = [*first[1 + self.hull.n :], *first[: 1 + self.hull.n]]
        witnesses = [{} for _ in self.V]
        for lam in order:
            for k, pixel in enumerate(self.poses.pixels(lam)):
                witnesses[k].setdefault(int(pixel), lam)
        search = dict(self.search, samples=0)
        return search_regions(
            self.backbone, self.hull, self.centers, 1, search, witnesses=witnesses
        )


def _listed(values) -> list | None:
    """``values`` (an array) as a list, None as None."""
    return None if values is None else values.tolist()


def _first_points(hull, sample_seed: int, samples: int = 64) -> list[torch.Tensor]:
    """λ of the seed image, the hull's other vertices and ``samples`` random images."""
    corners = torch.eye(hull.n, dtype=torch.float64)
    random = hull.sample(samples, sample_seed).to(torch.float64)
    return [torch.zeros(hull.n, dtype=torch.float64), *corners, *random]
