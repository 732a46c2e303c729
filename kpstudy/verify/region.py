"""The bounds of one network value over ``B`` regions: what every bound rule takes and gives.

A value is bounded by two affine functions of the input set's parameters ``θ``, stored
as coefficient stacks ``(B, q, *S)`` in centre/radius form (lower ``mid − rad``, upper
``mid + rad``; row 0 the constant, rows ``1 … q−1`` the ``θ`` coefficients), with ``θ``
in a *domain*: the simplex ``{θ ≥ 0, Σ θ ≤ 1}`` (a convex hull), the unit cube (a
parallelotope), or ``'point'`` (an interval, ``q = 1``: no ``θ``). Past the ``q`` rows,
``mid`` holds a zonotope's error-symbol coefficients, each symbol in ``[−1, 1]``; or the
symbols are held in spatial blocks (:mod:`kpstudy.verify.symbols`).
"""

from __future__ import annotations

import torch

from kpstudy.verify import symbols


def domain_min(a: torch.Tensor, domain: str) -> torch.Tensor:
    """Exact minimum over ``θ`` of ``a[:, 0] + Σ_i a[:, i] θ_i`` for ``a (B, q, …)``."""
    if a.shape[1] == 1 or domain == "point":
        return a[:, 0]
    rest = a[:, 1:]
    if domain == "simplex":
        return a[:, 0] + rest.min(1).values.clamp_max(0.0)
    if domain == "cube":
        return a[:, 0] + rest.clamp_max(0.0).sum(1)
    raise ValueError(f"domain: expected 'simplex', 'cube' or 'point', got {domain!r}")


def symbol_reach(a: torch.Tensor, q: int):
    """``Σ_e |a[:, q + e]|``: how far the error symbols move each entry (0 without any)."""
    return symbols.l1_rows(a[:, q:]) if a.shape[1] > q else 0.0


class Region:
    """``B`` regions of a value: coefficient stacks ``mid``, ``rad`` ``(B, q, *S)`` and a
    domain; a zonotope's error symbols either as rows of ``mid`` past ``q`` or as spatial
    ``blocks`` (:mod:`kpstudy.verify.symbols`; ``None`` when ``mid`` is dense), ``rows``
    then the dense stack's rows they number into (on a pass's output; inside a pass,
    :attr:`kpstudy.verify.operators.Pass.made`)."""

    def __init__(
        self,
        mid: torch.Tensor,
        rad: torch.Tensor,
        domain: str,
        blocks: list | None = None,
        rows: int | None = None,
    ) -> None:
        self.mid, self.rad, self.domain = mid, rad, domain
        self.blocks, self.rows = blocks, rows

    def reach(self) -> torch.Tensor | float:
        """``Σ_e |coefficient of symbol e|`` per entry ``(B, *S)`` (0 without symbols)."""
        if self.blocks is not None:
            return symbols.reach(self.blocks, self.mid[:, 0])
        return symbol_reach(self.mid, self.rad.shape[1])

    def symbols_at(self, index: torch.Tensor) -> torch.Tensor:
        """The error symbols' coefficients ``(B, E, n)`` on the flat entries ``index (n,)``."""
        q = self.rad.shape[1]
        if self.blocks is not None:
            return symbols.gather(self.blocks, self.rows - q, q, self.mid, index)
        return self.mid[:, q:].flatten(2).index_select(-1, index)

    @classmethod
    def affine(cls, coeff: torch.Tensor, domain: str) -> Region:
        """Exact affine inputs ``coeff (B, q, *S)`` over ``domain``."""
        return cls(coeff, torch.zeros_like(coeff), domain)

    @classmethod
    def between(cls, low: torch.Tensor, up: torch.Tensor, domain: str) -> Region:
        """The value between the affine functions ``low`` and ``up`` ``(B, q, *S)``."""
        return cls((up + low) / 2, (up - low) / 2, domain)

    @classmethod
    def interval(cls, lower: torch.Tensor, upper: torch.Tensor) -> Region:
        """Boxes ``lower, upper (B, *S)``."""
        return cls.between(lower[:, None], upper[:, None], "point")

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Concrete lower and upper bounds ``(B, *S)`` over the domain and the symbols."""
        q = self.rad.shape[1]
        spread = self.reach()
        low = domain_min(self.mid[:, :q] - self.rad, self.domain) - spread
        high = -domain_min(-(self.mid[:, :q] + self.rad), self.domain) + spread
        return low, high

    def without_symbols(self) -> Region:
        """The same bounds with the error symbols' reach moved into the radius (sound;
        what the symbols share is lost)."""
        q = self.rad.shape[1]
        rad = self.rad.clone()
        rad[:, 0] += self.reach()
        return Region(self.mid[:, :q], rad, self.domain)

    def select(self, rows: torch.Tensor) -> Region:
        """The regions ``rows`` (bool ``(B,)`` or indices) of the batch."""
        blocks = self.blocks
        if blocks is not None:
            blocks = [symbols.Block(b.coeff[rows], b.start, b.y[rows], b.x[rows]) for b in blocks]
        return Region(self.mid[rows], self.rad[rows], self.domain, blocks, self.rows)

    def to_interval(self) -> Region:
        return Region.interval(*self.bounds())

    @property
    def batch(self) -> int:
        return self.mid.shape[0]
