"""Verification-friendly training: random hulls of the study's kinds and a bound term.

Certified training (Gowal et al. 2018; Zhang et al. 2020; Shi et al. 2021) adds to the
natural loss a loss on *sound bounds* of the network over perturbation sets, so that the
trained network is one its verifier can prove things about. Here the sets are convex
hulls of the study's kinds, drawn afresh for every batch in model-input space
(:class:`HullSampler`): the image and 1–4 copies with an occluder patch (rendered by
data_gen from its meshes) pasted at a random place, the image ± a brightness or contrast
change, or 1–4 copies with a 3×3 block of random values. The bounds are kpstudy.verify's
own (:func:`hull_bounds`, method ``'forward'`` on a differentiable graph), and the term
(:func:`robust_heatmap_loss`) is the heatmap loss's worst case over the hull, bounded
above: ``Σ t log t − Σ_j t_j l_j + log Σ_j exp u_j`` for the target distribution ``t``
and the bounds ``l ≤ heatmap ≤ u``. It equals the natural loss when the bounds are tight
and grows with their width where it matters: low at the keypoint, high elsewhere, which
is what the proxy's "the keypoint's cell wins" needs.
"""

from __future__ import annotations

import contextlib
import math

import cv2
import numpy as np
import torch

from kpstudy import _checks
from kpstudy.verify.bounds import ZONOTOPE_ELEMENTS, Region, propagate
from kpstudy.verify.graph import Graph, trace

#: Bound methods of the term (:func:`hull_bounds`).
BOUND_METHODS = ("zonotope", "forward")
#: Hull kinds drawn by :class:`HullSampler` and their probabilities.
KINDS = {"objects": 0.5, "blocks": 0.2, "brightness": 0.15, "contrast": 0.15}
PHOTOMETRIC = ("brightness", "contrast")  # the kinds that change every pixel a little
#: Perturbed images of an object or block hull (the study's m ≤ 4).
MAX_COPIES = 4
#: Side of a pixel block, input pixels (data_gen.perturb.BLOCK).
BLOCK = 3
BRIGHTNESS = 2.0 / 255  # the study's largest brightness change, in [0, 1] units
CONTRAST = 1e-2  # the study's largest contrast change


def occluder_patches(px_per_m: float = 3.0, seed: int = 0) -> list[np.ndarray]:
    """One RGBA patch ``(h, w, 4)`` float32 per occluder of data_gen's catalog (colour in
    [0, 255], alpha in [0, 1]), rendered top-down with its shadow at ``px_per_m`` under a
    sun drawn with ``seed``, at a random yaw."""
    from data_gen.occluders import occluder_catalog
    from data_gen.patches import PatchRenderer
    from data_gen.render import Light

    rng = np.random.default_rng([seed, 7])
    renderer = PatchRenderer()
    patches = []
    for occluder in occluder_catalog():
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(np.deg2rad(30), np.deg2rad(80))
        light = Light(np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]))
        patch = renderer.render(
            occluder.name, occluder.mesh, px_per_m, light, float(rng.uniform(0, 360))
        )
        if patch.size:
            patches.append(patch)
    return patches


def photometric_pair(image: np.ndarray, kind: str, rng: np.random.Generator) -> np.ndarray:
    """The two perturbed images ``(2, 3, s, s)`` of a random brightness (``image ± d``,
    ``d`` uniform in [0, ``BRIGHTNESS``]) or contrast (``image · (1 ± c)``, ``c`` uniform
    in [0, ``CONTRAST``]) hull around ``image (3, s, s)`` in [0, 1], clipped to [0, 1]."""
    _checks.choice(kind, "kind", PHOTOMETRIC)
    if kind == "brightness":
        d = rng.uniform(0, BRIGHTNESS)
        return np.stack([np.clip(image + d, 0, 1), np.clip(image - d, 0, 1)])
    c = rng.uniform(0, CONTRAST)
    return np.stack([np.clip(image * (1 + c), 0, 1), np.clip(image * (1 - c), 0, 1)])


def relu_instability(centre: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """How deep the ReLUs after an affine layer sit inside their unstable band over a hull.

    ``centre (B, C, *S)``: the layer's pre-activations at each hull's first vertex (the
    image), ``C`` channels; ``deltas (B, n, C, *S)``: their changes at its other ``n``
    vertices. An affine map takes its extremes on a simplex at the vertices, so over the
    hull each pre-activation spans exactly ``[l, u] = centre + [min(0, δ), max(0, δ)]`` and
    its ReLU is unstable where ``l < 0 < u`` (a ReLU stability term, after Xiao et al.
    2019). Returns the mean over hulls and units of ``min(−l, u)⁺``, the distance to the
    nearer end of the band (0 for a stable ReLU), in units of its channel's spread over the
    batch (a constant): a scalar whose gradient narrows the band and moves its centre out.
    """
    low = centre + deltas.amin(1).clamp_max(0.0)
    high = centre + deltas.amax(1).clamp_min(0.0)
    depth = torch.minimum(-low, high).clamp_min(0.0)
    dims = [d for d in range(centre.ndim) if d != 1]
    spread = centre.detach().std(dims, keepdim=True).clamp_min(1e-12)
    return (depth / spread).mean()


def block_image(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A copy of ``image (3, H, W)`` in [0, 1] with a :data:`BLOCK` × :data:`BLOCK` block of
    uniform random values at a uniform random place (the study's block occlusion)."""
    _, H, W = image.shape
    y, x = rng.integers(0, H - BLOCK + 1), rng.integers(0, W - BLOCK + 1)
    out = image.copy()
    out[:, y : y + BLOCK, x : x + BLOCK] = rng.uniform(0, 1, (3, BLOCK, BLOCK))
    return out


def block_hull_points(images: torch.Tensor, rng: np.random.Generator, interior: int = 1):
    """Points ``(B, 1 + MAX_COPIES + interior, 3, s, s)`` of a random block hull around each
    image of ``images (B, 3, s, s)`` in [0, 1]: the image, :data:`MAX_COPIES` copies with a
    block each (:func:`block_image`), then ``interior`` uniform random points of the hull."""
    x = images.detach().float().cpu().numpy()
    vertices = np.stack(
        [np.stack([im] + [block_image(im, rng) for _ in range(MAX_COPIES)]) for im in x]
    )
    weights = rng.dirichlet(np.ones(1 + MAX_COPIES), (len(x), interior))
    inner = np.einsum("bpk,bkchw->bpchw", weights, vertices)
    points = np.concatenate([vertices, inner], 1).astype(np.float32)
    return torch.from_numpy(points).to(images.device)


class HullSampler:
    """Random convex hulls of the study's kinds around model-input images.

    Parameters
    ----------
    patches : list of ndarray (h, w, 4)
        Occluder patches (:func:`occluder_patches`).
    aspect : (float, float)
        Resize factors ``(sx, sy)`` of the dataset's images to the model input (a patch at
        the image's resolution shrinks by them): data_gen's 640×400 renders at 64×64 give
        (0.1, 0.16).
    seed : int
    patch_px : (float, float)
        Range of a pasted patch's longer side, in image pixels before the resize (the
        study's occluders span 8–150 px at 1920 px width, 2.7–50 px at 640).
    """

    def __init__(self, patches, aspect=(0.1, 0.16), seed: int = 0, patch_px=(3.0, 50.0)):
        if not patches:
            raise ValueError("patches: expected at least one occluder patch")
        self.patches = list(patches)
        self.aspect = tuple(float(a) for a in aspect)
        self.patch_px = tuple(float(p) for p in patch_px)
        self.seed = seed
        self.reseed(0)

    def reseed(self, epoch: int) -> None:
        """Draw from the stream of ``epoch`` (a resumed training run draws the same hulls)."""
        self.rng = np.random.default_rng([self.seed, 11, epoch])

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """Hull vertices ``(B, 1 + MAX_COPIES, 3, s, s)`` of images ``(B, 3, s, s)`` in
        [0, 1]: row 0 the image itself; hulls with fewer perturbed images repeat it (a
        zero direction adds nothing to the hull)."""
        x = images.detach().cpu().numpy()
        out = np.repeat(x[:, None], 1 + MAX_COPIES, 1)
        kinds, p = list(KINDS), np.array(list(KINDS.values()))
        for b in range(len(x)):
            kind = kinds[self.rng.choice(len(kinds), p=p / p.sum())]
            if kind in PHOTOMETRIC:
                out[b, 1:3] = photometric_pair(x[b], kind, self.rng)
            else:
                paint = self._paste if kind == "objects" else self._block
                for k in range(1, 1 + self.rng.integers(1, MAX_COPIES + 1)):
                    out[b, k] = paint(x[b])
        return torch.from_numpy(out).to(images.device, images.dtype)

    def _block(self, image: np.ndarray) -> np.ndarray:
        return block_image(image, self.rng)

    def _paste(self, image: np.ndarray) -> np.ndarray:
        """One patch, resized to a random size at the input's scale, alpha-composited at a
        random place (a patch smaller than a pixel covers one pixel with its area as alpha)."""
        patch = self.patches[self.rng.integers(len(self.patches))]
        h, w = patch.shape[:2]
        side = self.rng.uniform(*self.patch_px) / max(h, w)  # image pixels per patch pixel
        ww, hh = w * side * self.aspect[0], h * side * self.aspect[1]
        size = (max(1, round(ww)), max(1, round(hh)))
        rgba = patch.copy()
        rgba[..., :3] *= rgba[..., 3:]  # premultiplied: colour and coverage average together
        rgba = cv2.resize(rgba, size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], 4)
        rgba[..., 3] *= min(1.0, ww) * min(1.0, hh)  # sub-pixel patches cover part of a pixel
        alpha = rgba[..., 3]
        colour = rgba[..., :3] / np.maximum(rgba[..., 3:], 1e-6)
        _, H, W = image.shape
        y, x = self.rng.integers(0, H - size[1] + 1), self.rng.integers(0, W - size[0] + 1)
        out = image.copy()
        region = out[:, y : y + size[1], x : x + size[0]]
        out[:, y : y + size[1], x : x + size[0]] = (
            region * (1 - alpha) + (np.clip(colour, 0, 255).transpose(2, 0, 1) / 255.0) * alpha
        )
        return out


class BatchStatistics:
    """Batch norms that normalise the bound pass by the natural pass's batch statistics.

    Bounds are computed with every batch norm a fixed affine map (eval mode). With the
    running statistics, the bound term would train another network than the natural term
    does (train mode, the batch's statistics); measured on the affine-decoder CNN after
    four epochs of the term: validation PCK@2 0.50 in eval mode against 0.77 with batch
    statistics, the same weights. So, as Shi et al. (2021) do, the statistics of each
    batch's natural pass (recorded by forward hooks, detached) stand in for the running
    ones while the bounds are computed (:meth:`frozen`); the running statistics, which
    the verified network uses, are the usual average of those.
    """

    def __init__(self, backbone: torch.nn.Module) -> None:
        self.backbone = backbone
        self.norms = [m for m in backbone.modules() if isinstance(m, torch.nn.BatchNorm2d)]
        self.batch: dict[torch.nn.Module, tuple] = {}
        for m in self.norms:
            m.register_forward_hook(self._record)

    def _record(self, m, inputs, output) -> None:
        if m.training:
            x = inputs[0].detach()
            self.batch[m] = (x.mean((0, 2, 3)), x.var((0, 2, 3), unbiased=False))

    @contextlib.contextmanager
    def frozen(self):
        """Eval mode with the last natural pass's batch statistics; restores both."""
        missing = [m for m in self.norms if m not in self.batch]
        if missing:
            raise RuntimeError("backbone: run a natural pass in train mode first")
        mode = self.backbone.training
        running = [(m.running_mean, m.running_var) for m in self.norms]
        for m in self.norms:
            m.running_mean, m.running_var = self.batch[m]
        self.backbone.eval()
        try:
            yield
        finally:
            self.backbone.train(mode)
            for m, (mean, var) in zip(self.norms, running):
                m.running_mean, m.running_var = mean, var


def bound_graph(backbone: torch.nn.Module) -> Graph:
    """The differentiable graph of ``backbone`` (traced in eval mode, the mode the bounds
    must be computed in)."""
    mode = backbone.training
    backbone.eval()
    try:
        s = backbone.input_size
        example = torch.zeros(1, 3, s, s, dtype=next(backbone.parameters()).dtype)
        return trace(backbone, example, differentiable=True)
    finally:
        backbone.train(mode)


def hull_bounds(graph: Graph, vertices: torch.Tensor, scale: float = 1.0, method="zonotope"):
    """Sound lower and upper bounds ``(B, K, H, W)`` of the heatmaps over each hull.

    ``vertices (B, n+1, 3, s, s)``: row 0 the image, rows 1… the perturbed images; the
    hull is shrunk towards the image by ``scale`` ∈ [0, 1] (a warm-up schedule).
    ``method``: ``'zonotope'`` (DeepZ error symbols: exact through affine layers, the
    verifier's own method) or ``'forward'`` (linear bounds in λ with interval coefficients,
    triangle ReLUs: ~10⁴–10⁶× looser on a trained CNN, ~10× cheaper). Differentiable in the
    graph's parameters when it was traced ``differentiable`` (its batch norms in eval mode).
    """
    if not 0.0 <= scale <= 1.0:
        raise ValueError(f"scale: expected a number in [0, 1], got {scale!r}")
    _checks.choice(method, "method", BOUND_METHODS)
    origin = vertices[:, :1]
    coeff = torch.cat([origin, (vertices[:, 1:] - origin) * scale], 1)
    # Autograd keeps every symbol's windows for the backward pass: as many symbols as a
    # dense stack of ZONOTOPE_ELEMENTS holds (without the cap the footprint budget admits
    # far more, and training ran out of memory).
    biggest = max(math.prod(n.shape) for n in graph.nodes)
    out, _ = propagate(
        graph,
        Region.affine(coeff, "simplex"),
        zonotope=method == "zonotope",
        max_generators=max(0, ZONOTOPE_ELEMENTS // biggest - coeff.shape[1]),
    )
    return out.bounds()


def robust_heatmap_loss(lower, upper, keypoints, weights, sigma: float) -> torch.Tensor:
    """Upper bound of the heatmap KL loss over every heatmap between ``lower`` and
    ``upper`` ``(B, K, H, W)``: ``Σ t log t − Σ t·l + logsumexp(u)`` per keypoint, averaged
    over the keypoints with ``weights (B, K)`` > 0 (targets ``t`` as
    :func:`kpstudy.models.training.heatmap_targets` at ``keypoints (B, K, 2)``, heatmap pixels)."""
    from kpstudy.models.training import heatmap_targets

    H = lower.shape[-1]
    t = heatmap_targets(keypoints, H, sigma).flatten(2)
    entropy = (t * torch.log(t.clamp_min(1e-30))).sum(-1)
    loss = entropy - (t * lower.flatten(2)).sum(-1) + torch.logsumexp(upper.flatten(2), -1)
    return (loss * weights).sum() / weights.sum().clamp_min(1.0)
