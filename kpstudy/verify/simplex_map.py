"""The box ``[0, 1]^n`` mapped exactly onto the simplex, by matrix products and ReLUs only.

Most verifiers of the VNN-COMP accept box inputs only, while a convex hull of ``n + 1``
images is parametrised by the simplex ``{λ ≥ 0, Σ λ ≤ 1}``. :class:`BoxToSimplex` closes
the gap inside the network: sort ``u ∈ [0, 1]^n`` ascending and take the spacings

    ``λ_1 = u_(1)``,  ``λ_i = u_(i) − u_(i−1)``  (``i = 2 … n``),

so ``λ ≥ 0`` and ``Σ λ = u_(n) ≤ 1``; conversely every ``λ`` of the simplex is the image
of ``u = cumsum(λ)`` (sorted, in ``[0, 1]^n``). The map is onto, piecewise linear and
continuous, so a box-input verifier that reads the exported network verifies exactly the
hull. The sort is an odd–even transposition network of ``n`` rounds; each comparator is
``min(a, b) = a − relu(a − b)``, ``max(a, b) = b + relu(a − b)``, so the layer is
``MatMul``, ``Relu`` and ``Add`` in ONNX (exact in real arithmetic: its matrices hold only
0 and ±1). The sorted ``u`` (``≥ 0``, also in floating point) then passes one more ``Relu``,
the identity there: without it the comparators' skip connections (``a + …``) give the
linear layers after the sort two sources, and Marabou 2.0.0 (its network-level reasoner's
``mergeWSLayers``) adds the bias of such a layer once per source when it merges the layer
into the next linear one, i.e. counts the hull's ``X0`` twice.

The layer returns the barycentric weights ``w = (1 − Σ λ, λ_1 … λ_n)`` of the ``n + 1``
vertices, so that the image ``w @ V`` uses the vertices themselves (not rounded
differences ``X_i − X0``). :class:`SimplexWeights` is the same map for an input that is
already ``λ`` (the ``Σ λ ≤ 1`` form, or a parallelotope's cube).
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["BoxToSimplex", "SimplexWeights", "box_of_lambda", "lambda_of_box"]


def _comparators(n: int) -> list[list[tuple[int, int]]]:
    """Rounds of disjoint ``(i, i + 1)`` pairs of the odd–even transposition sort of ``n``."""
    return [[(i, i + 1) for i in range(r % 2, n - 1, 2)] for r in range(n)]


class SimplexWeights(nn.Module):
    """``λ (B, n) ↦ w (B, n+1) = (1 − Σ λ, λ)``: barycentric weights of the vertices."""

    def __init__(self, n: int, dtype=torch.float32) -> None:
        super().__init__()
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"n: expected an integer >= 1, got {n!r}")
        self.n = n
        weight = torch.cat([-torch.ones(n, 1), torch.eye(n)], 1)  # (n, n+1)
        bias = torch.zeros(n + 1)
        bias[0] = 1.0
        self.register_buffer("weight", weight.to(dtype))
        self.register_buffer("bias", bias.to(dtype))

    def linear(self, lam: torch.Tensor) -> torch.Tensor:
        """``w − e_0``, the part of ``w`` linear in ``λ``: ``(−Σ λ, λ)``."""
        return lam @ self.weight

    def forward(self, lam: torch.Tensor) -> torch.Tensor:
        return self.linear(lam) + self.bias


class BoxToSimplex(nn.Module):
    """``u (B, n) ∈ [0, 1]^n ↦ w (B, n+1)``: sort ``u``, take its spacings ``λ``, return
    ``(1 − Σ λ, λ)`` (see the module docstring); onto the simplex's barycentric weights.

    Parameters
    ----------
    n : int
        Simplex dimension (perturbed images of the hull), ``>= 1``.
    dtype : torch.dtype
        Of the fixed matrices (all entries 0 or ±1, exact in any float dtype).

    Examples
    --------
    >>> BoxToSimplex(3)(torch.tensor([[0.7, 0.2, 0.5]]))
    tensor([[0.3000, 0.2000, 0.3000, 0.2000]])
    """

    def __init__(self, n: int, dtype=torch.float32) -> None:
        super().__init__()
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"n: expected an integer >= 1, got {n!r}")
        self.n = n
        self.rounds = 0
        for pairs in _comparators(n):
            if not pairs:
                continue
            diff = torch.zeros(n, len(pairs))  # u @ diff: a − b per comparator
            swap = torch.zeros(len(pairs), n)  # relu(a − b) @ swap: −d to a, +d to b
            for k, (i, j) in enumerate(pairs):
                diff[i, k], diff[j, k] = 1.0, -1.0
                swap[k, i], swap[k, j] = -1.0, 1.0
            self.register_buffer(f"diff{self.rounds}", diff.to(dtype))
            self.register_buffer(f"swap{self.rounds}", swap.to(dtype))
            self.rounds += 1
        # sorted u ↦ w: w_0 = 1 − u_(n), w_i = u_(i) − u_(i−1)
        spacing = torch.zeros(n, n + 1)
        spacing[n - 1, 0] = -1.0
        for i in range(n):
            spacing[i, i + 1] = 1.0
            if i:
                spacing[i - 1, i + 1] = -1.0
        bias = torch.zeros(n + 1)
        bias[0] = 1.0
        self.register_buffer("spacing", spacing.to(dtype))
        self.register_buffer("bias", bias.to(dtype))

    def linear(self, u: torch.Tensor) -> torch.Tensor:
        """``w − e_0 = (−u_(n), λ)``: the sort and the spacings, without the constant."""
        for r in range(self.rounds):
            u = u + torch.relu(u @ getattr(self, f"diff{r}")) @ getattr(self, f"swap{r}")
        if self.rounds:
            u = torch.relu(u)  # the identity on sorted u ≥ 0; cuts the skip connections
        return u @ self.spacing

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return self.linear(u) + self.bias


def lambda_of_box(u) -> torch.Tensor:
    """The simplex point ``λ (…, n)`` of box points ``u (…, n)``, float64, computed
    directly (a sort and differences): what :class:`BoxToSimplex` computes with ReLUs."""
    s = torch.sort(torch.as_tensor(u, dtype=torch.float64), dim=-1).values
    return torch.cat([s[..., :1], s[..., 1:] - s[..., :-1]], -1)


def box_of_lambda(lam) -> torch.Tensor:
    """A box point ``u = cumsum(λ)`` (float64) that :class:`BoxToSimplex` maps to ``λ``."""
    return torch.cumsum(torch.as_tensor(lam, dtype=torch.float64), -1)
