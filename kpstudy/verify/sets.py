"""Input sets of the verifier: the exact convex hull, its parallelotope relaxation, boxes.

Every set is the image of a small parameter domain under an affine map into image
space. A :class:`ConvexHull` of ``n + 1`` images is ``X0 + D λ`` with ``λ`` in the
simplex ``{λ ≥ 0, Σ λ ≤ 1}`` (``D`` stacks the directions ``X_i − X0``); a
:class:`Parallelotope` is the same map on the cube ``λ ∈ [0, 1]^n`` (how
ModelVerification.jl treats a hull: a superset with ``n!`` times the volume); a
:class:`Box` is ``lower ≤ x ≤ upper``, the ℓ∞ baseline.

Branch and bound works on *nodes*: a sub-simplex (its ``n + 1`` vertices in λ), a
sub-cube (``lo, hi`` in λ) or a sub-box (``lower, upper`` images). The bound engine only
needs each node's ``kpstudy.verify.region.Region``: its affine input
``x = c + Σ_i θ_i G_i`` over a domain (``'simplex'`` or ``'cube'``) or, for a box, its
interval.

A set type is one class, which gives what the verifier asks of a set (besides its
``dtype`` and ``n``, the parameters of a point):

* ``example_input()``, a model input ``(1, *S)`` (to trace the model), and ``rows``, the
  coefficient rows ``q`` of its regions (to size a batch);
* ``root()``, ``split(nodes)`` and ``region(nodes, dtype)``: the nodes of branch and
  bound and what the bound engine starts from;
* ``node_points(nodes)``, the points an attack tries first, and for its gradient descent
  ``centre_weights(nodes)``, ``node_point(nodes, weights)`` and ``project_weights(w)``:
  each node's points as weights within it;
* ``image(points)``, ``contains_point(points)`` and ``clip(points)`` (a point pulled into
  the set where rounding left it a hair outside), ``contains(image)``, ``sample(…)``.
"""

from __future__ import annotations

import math

import torch

from kpstudy.verify.region import Region


class ConvexHull:
    """The exact convex hull of ``n + 1`` images.

    ``{X0 + Σ_i λ_i (X_i − X0) : λ ≥ 0, Σ λ ≤ 1}``.

    Parameters
    ----------
    vertices : Tensor, shape ``(n+1, *S)``
        ``X0`` (the seed image) first, then the ``n`` perturbed images (preprocessed, as
        the model takes them; ``S`` is e.g. ``(3, 64, 64)``).

    Examples
    --------
    >>> hull = ConvexHull(torch.tensor([[0.0, 0.0], [4.0, 0.0], [0.0, 8.0]]))
    >>> hull.image(torch.tensor([0.5, 0.25]))  # 0.25 X0 + 0.5 X1 + 0.25 X2
    tensor([2., 2.])
    """

    #: The domain of λ in its regions (``kpstudy.verify.region.domain_min()``).
    domain = "simplex"

    def __init__(self, vertices) -> None:
        if not isinstance(vertices, torch.Tensor):
            raise ValueError(
                f"vertices: expected a torch.Tensor of shape (n+1, *image_shape), got "
                f"{type(vertices).__name__}"
            )
        if vertices.ndim < 2 or vertices.shape[0] < 2:
            raise ValueError(
                "vertices: expected shape (n+1, *image_shape) with at least two images "
                f"(a seed and one perturbed image), got {tuple(vertices.shape)}"
            )
        if not vertices.is_floating_point():
            raise ValueError(f"vertices: expected a floating-point tensor, got {vertices.dtype}")
        if not torch.isfinite(vertices).all():
            raise ValueError("vertices: expected finite values, got NaN or inf")
        self.vertices = vertices.detach()
        self.dtype = vertices.dtype
        self.shape = tuple(vertices.shape[1:])
        self.n = vertices.shape[0] - 1
        v64 = self.vertices.to(torch.float64)
        self.origin = v64[0]  # X0, float64
        self.directions = v64[1:] - v64[:1]  # D, (n, *S), float64
        flat = self.directions.reshape(self.n, -1)
        self.gram = flat @ flat.T  # DᵀD, (n, n): image-space lengths of λ-space edges

    @property
    def rows(self) -> int:
        """Coefficient rows of a region: the constant and one per parameter."""
        return self.n + 1

    def example_input(self) -> torch.Tensor:
        """``X0`` as a model input ``(1, *S)``."""
        return self.vertices[0][None]

    # -- points -------------------------------------------------------------------------
    def image(self, lam, dtype=None) -> torch.Tensor:
        """Images ``X0 + D λ`` for ``lam (..., n)``, shape ``(..., *S)``, computed in float64
        and returned in ``dtype`` (default the vertices' dtype; ``torch.float64`` gives the
        set's exact point to float64 rounding)."""
        lam = torch.as_tensor(lam, dtype=torch.float64)
        if lam.shape[-1:] != (self.n,):
            raise ValueError(f"lam: expected shape (..., {self.n}), got {tuple(lam.shape)}")
        flat = lam.reshape(-1, self.n) @ self.directions.reshape(self.n, -1)
        out = self.origin.reshape(1, -1) + flat
        return out.reshape(*lam.shape[:-1], *self.shape).to(dtype or self.dtype)

    def contains_point(self, lam, tol: float = 0.0) -> torch.Tensor:
        """Points of a hull are λ: :meth:`contains_lambda`."""
        return self.contains_lambda(lam, tol)

    def contains(self, image, tol: float = 1e-6) -> bool:
        """Whether ``image`` (shape ``S``) is a point of the set, to ``tol`` (max abs pixel)."""
        x = torch.as_tensor(image, dtype=torch.float64)
        if tuple(x.shape) != self.shape:
            raise ValueError(f"image: expected shape {self.shape}, got {tuple(x.shape)}")
        D = self.directions.reshape(self.n, -1).T  # (d, n)
        lam = torch.linalg.lstsq(D, (x - self.origin).reshape(-1, 1)).solution[:, 0]
        residual = (D @ lam - (x - self.origin).reshape(-1)).abs().max()
        return bool(residual <= tol and self.contains_lambda(lam, tol=tol))

    def sample(self, count: int, seed: int, kind: str = "dirichlet") -> torch.Tensor:
        """``count`` parameter points ``λ (count, n)`` of the set, float64.

        ``kind``: ``'dirichlet'`` (uniform over the domain), ``'vertices'`` (its corners)
        or ``'edges'`` (uniform points on random edges).
        """
        if kind not in ("dirichlet", "vertices", "edges"):
            raise ValueError(f"kind: expected 'dirichlet', 'vertices' or 'edges', got {kind!r}")
        if not (isinstance(count, int) and count >= 1):
            raise ValueError(f"count: expected an integer >= 1, got {count!r}")
        g = torch.Generator().manual_seed(seed)
        corners = self._corners()
        if kind == "vertices":
            return corners[torch.randint(len(corners), (count,), generator=g)]
        if kind == "edges":
            i = torch.randint(len(corners), (count,), generator=g)
            j = (i + torch.randint(1, len(corners), (count,), generator=g)) % len(corners)
            s = torch.rand(count, 1, generator=g, dtype=torch.float64)
            return corners[i] + s * (corners[j] - corners[i])
        return self._uniform(count, g)

    def contains_lambda(self, lam, tol: float = 0.0) -> torch.Tensor:
        """Whether each ``lam (..., n)`` lies in the parameter domain (to ``tol``)."""
        lam = torch.as_tensor(lam, dtype=torch.float64)
        return (lam >= -tol).all(-1) & (lam.sum(-1) <= 1.0 + tol)

    def clip(self, lam: torch.Tensor) -> torch.Tensor:
        """``lam (..., n)`` pulled exactly into the domain (rounding can leave λ a hair
        outside)."""
        lam = lam.clamp_min(0.0)
        total = lam.sum(-1, keepdim=True)
        lam = torch.where(total > 1.0, lam / total, lam)
        return torch.where(lam.sum(-1, keepdim=True) > 1.0, lam * (1 - 1e-12), lam)

    def _corners(self) -> torch.Tensor:
        return torch.cat([torch.zeros(1, self.n, dtype=torch.float64), torch.eye(self.n).double()])

    def _uniform(self, count: int, g: torch.Generator) -> torch.Tensor:
        e = -torch.log(torch.rand(count, self.n + 1, generator=g, dtype=torch.float64))
        return (e / e.sum(-1, keepdim=True))[:, 1:]  # flat Dirichlet weights, X0's dropped

    def root(self) -> torch.Tensor:
        """Node ``(1, n+1, n)``: the λ-coordinates of the simplex's vertices."""
        return self._corners()[None]

    def region(self, nodes, dtype) -> Region:
        """The regions of ``B`` nodes: their affine inputs ``x = c + Σ θ_i G_i``,
        coefficients ``[c, G_1 … G_n]`` ``(B, n+1, *S)`` in ``dtype``, ``θ`` in the
        set's :attr:`domain`."""
        return Region.affine(self._lift(self._affine(nodes), dtype), self.domain)

    def _affine(self, nodes):
        """The λ-space affine maps ``(B, n+1, n)`` of the nodes: a vertex, then the edges
        from it to the others."""
        c = nodes[:, 0]  # (B, n)
        return torch.cat([c[:, None], nodes[:, 1:] - c[:, None]], 1)

    def split(self, nodes: torch.Tensor) -> torch.Tensor:
        """Bisect each node's longest edge (image-space length): ``(2B, n+1, n)``; the two
        children share the midpoint and exactly cover the parent."""
        diff = nodes[:, :, None] - nodes[:, None, :]  # (B, n+1, n+1, n)
        length2 = torch.einsum("bijk,kl,bijl->bij", diff, self.gram, diff)
        flat = length2.flatten(1).argmax(1)
        i, j = flat // (self.n + 1), flat % (self.n + 1)
        rows = torch.arange(len(nodes))
        mid = 0.5 * (nodes[rows, i] + nodes[rows, j])
        left, right = nodes.clone(), nodes.clone()
        left[rows, i] = mid
        right[rows, j] = mid
        return torch.cat([left, right])

    def node_points(self, nodes: torch.Tensor) -> torch.Tensor:
        """Candidate points of each node: its vertices and centroid, λ ``(B, n+2, n)``."""
        return torch.cat([nodes, nodes.mean(1, keepdim=True)], 1)

    def node_point(self, nodes: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """λ ``(B, n)`` of barycentric ``weights (B, n+1)`` in each node."""
        return torch.einsum("bv,bvn->bn", weights, nodes)

    def centre_weights(self, nodes: torch.Tensor) -> torch.Tensor:
        """The weights ``(B, n+1)`` of each node's centroid."""
        return torch.full((len(nodes), nodes.shape[1]), 1.0 / nodes.shape[1], dtype=torch.float64)

    def project_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Each row of ``w (B, n+1)`` projected (Euclidean) onto the barycentric weights."""
        u, _ = torch.sort(w, dim=1, descending=True)
        css = u.cumsum(1) - 1.0
        k = torch.arange(1, w.shape[1] + 1, dtype=w.dtype)
        cond = u - css / k > 0
        rho = cond.to(torch.int64).cumsum(1).argmax(1, keepdim=True)
        theta = css.gather(1, rho) / (rho + 1).to(w.dtype)
        return (w - theta).clamp_min(0.0)

    def _lift(self, coeff, dtype):
        """Image-space coefficients of λ-space affine maps ``coeff (B, p+1, n)``
        (row 0 a point, rows 1… directions): ``(B, p+1, *S)`` in ``dtype``."""
        B, q, _ = coeff.shape
        img = coeff.reshape(B * q, self.n) @ self.directions.reshape(self.n, -1)
        img = img.reshape(B, q, -1)
        img[:, 0] += self.origin.reshape(1, -1)
        return img.reshape(B, q, *self.shape).to(dtype)


class _CornerNodes:
    """Nodes that are pairs of opposite corners ``(B, 2, …)``, a node's points given by
    weights in ``[0, 1]`` per coordinate: a sub-cube of λ, a sub-box of images."""

    def node_points(self, nodes):
        """Candidate points: the corners ``lo``, ``hi`` and the centre of each node."""
        return torch.cat([nodes, nodes.mean(1, keepdim=True)], 1)

    def node_point(self, nodes, weights):
        """The points at weights ``(B, …)`` in [0, 1] within each node."""
        return nodes[:, 0] + weights * (nodes[:, 1] - nodes[:, 0])

    def centre_weights(self, nodes):
        return torch.full((len(nodes), *nodes.shape[2:]), 0.5, dtype=torch.float64)

    def project_weights(self, w):
        return w.clamp(0.0, 1.0)


class Parallelotope(_CornerNodes, ConvexHull):
    """ModelVerification.jl's treatment of a hull: ``{X0 + D λ : λ ∈ [0, 1]^n}`` (baseline).

    A superset of :class:`ConvexHull` with ``n!`` times its volume: its points, and so its
    counterexamples, can lie outside the hull. Parameters as :class:`ConvexHull`.
    """

    domain = "cube"

    def contains_lambda(self, lam, tol: float = 0.0) -> torch.Tensor:
        lam = torch.as_tensor(lam, dtype=torch.float64)
        return ((lam >= -tol) & (lam <= 1.0 + tol)).all(-1)

    def clip(self, lam):
        return lam.clamp_min(0.0).clamp_max(1.0)

    def _corners(self) -> torch.Tensor:
        bits = torch.arange(2**self.n)[:, None] >> torch.arange(self.n)
        return (bits & 1).double()

    def _uniform(self, count: int, g: torch.Generator) -> torch.Tensor:
        return torch.rand(count, self.n, generator=g, dtype=torch.float64)

    def root(self) -> torch.Tensor:
        """Node ``(1, 2, n)``: the cube's ``lo`` and ``hi`` corners in λ."""
        return torch.stack([torch.zeros(self.n), torch.ones(self.n)]).double()[None]

    def _affine(self, nodes):
        lo, hi = nodes[:, 0], nodes[:, 1]
        return torch.cat([lo[:, None], torch.diag_embed(hi - lo)], 1)  # (B, n+1, n)

    def split(self, nodes):
        """Bisect each node's longest side (image-space length): ``(2B, 2, n)``."""
        width = (nodes[:, 1] - nodes[:, 0]) * self.gram.diagonal().sqrt()
        k = width.argmax(1)
        rows = torch.arange(len(nodes))
        mid = 0.5 * (nodes[rows, 0, k] + nodes[rows, 1, k])
        left, right = nodes.clone(), nodes.clone()
        left[rows, 1, k] = mid
        right[rows, 0, k] = mid
        return torch.cat([left, right])


class Box(_CornerNodes):
    """The ℓ∞ baseline ``{x : lower ≤ x ≤ upper}``.

    Parameters
    ----------
    lower, upper : Tensor, shape S
        Element-wise bounds, ``lower ≤ upper``.

    Bound propagation starts from the interval (linear bounds carry no input
    directions), and branch and bound halves the widest pixel.
    """

    rows = 1  # an interval: no parameter

    def __init__(self, lower, upper) -> None:
        for name, x in (("lower", lower), ("upper", upper)):
            if not isinstance(x, torch.Tensor) or not x.is_floating_point():
                raise ValueError(f"{name}: expected a floating-point torch.Tensor")
            if not torch.isfinite(x).all():
                raise ValueError(f"{name}: expected finite values, got NaN or inf")
        if lower.shape != upper.shape:
            raise ValueError(
                f"upper: expected the shape of lower {tuple(lower.shape)}, got {tuple(upper.shape)}"
            )
        if (lower > upper).any():
            raise ValueError("upper: expected upper >= lower everywhere")
        self.lower, self.upper = lower.detach(), upper.detach().to(lower.dtype)
        self.dtype = lower.dtype
        self.shape = tuple(lower.shape)
        self.n = math.prod(self.shape)

    def example_input(self) -> torch.Tensor:
        return self.lower[None]

    def image(self, x, dtype=None) -> torch.Tensor:
        """A box's points are images: ``x (..., *S)`` in ``dtype`` (default the box's)."""
        return torch.as_tensor(x).to(dtype or self.dtype)

    def clip(self, x: torch.Tensor) -> torch.Tensor:
        return torch.minimum(torch.maximum(x, self.lower), self.upper)

    def contains_point(self, x, tol: float = 0.0) -> torch.Tensor:
        """Whether each image ``x (..., *S)`` lies in the box (to ``tol``)."""
        x = torch.as_tensor(x, dtype=torch.float64)
        inside = (x >= self.lower - tol) & (x <= self.upper + tol)
        return inside.reshape(*x.shape[: x.ndim - len(self.shape)], -1).all(-1)

    def contains(self, image, tol: float = 1e-6) -> bool:
        x = torch.as_tensor(image, dtype=torch.float64)
        if tuple(x.shape) != self.shape:
            raise ValueError(f"image: expected shape {self.shape}, got {tuple(x.shape)}")
        return bool(((x >= self.lower - tol) & (x <= self.upper + tol)).all())

    def sample(self, count: int, seed: int, kind: str = "dirichlet") -> torch.Tensor:
        """``count`` images ``(count, *S)``: uniform (``'dirichlet'``), corners
        (``'vertices'``) or points on random edges between corners (``'edges'``)."""
        if kind not in ("dirichlet", "vertices", "edges"):
            raise ValueError(f"kind: expected 'dirichlet', 'vertices' or 'edges', got {kind!r}")
        g = torch.Generator().manual_seed(seed)
        theta = torch.rand(count, *self.shape, generator=g, dtype=self.dtype)
        if kind == "vertices":
            theta = theta.round()
        elif kind == "edges":
            corner = theta.round()
            free = torch.randint(self.n, (count,), generator=g)
            corner.view(count, -1)[torch.arange(count), free] = theta.view(count, -1)[
                torch.arange(count), free
            ]
            theta = corner
        return self.lower + theta * (self.upper - self.lower)

    def root(self) -> torch.Tensor:
        return torch.stack([self.lower, self.upper])[None]

    def region(self, nodes: torch.Tensor, dtype) -> Region:
        """The intervals of ``B`` nodes."""
        return Region.interval(nodes[:, 0].to(dtype), nodes[:, 1].to(dtype))

    def split(self, nodes):
        """Halve each node's widest pixel: ``(2B, 2, *S)``."""
        B = len(nodes)
        flat = nodes.reshape(B, 2, -1)
        k = (flat[:, 1] - flat[:, 0]).argmax(1)
        rows = torch.arange(B)
        mid = 0.5 * (flat[rows, 0, k] + flat[rows, 1, k])
        left, right = flat.clone(), flat.clone()
        left[rows, 1, k] = mid
        right[rows, 0, k] = mid
        return torch.cat([left, right]).reshape(2 * B, 2, *self.shape)
