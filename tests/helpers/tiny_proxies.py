"""Small keypoint-like proxies over hulls of perturbed images: the instances that the
outside verifiers (tests/test_marabou.py, tests/test_neuralsat.py) decide beside
:func:`kpstudy.verify.verify`."""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models.pooling import build_cell_pool
from kpstudy.verify import ConvexHull
from kpstudy.verify.spec import ArgmaxSpec

#: Heatmap side of :class:`TinyProxy`.
SIDE = 6


class TinyProxy(nn.Module):
    """Conv(1→3) → ReLU → Conv(3→2): two 6×6 heatmaps; each pooled into its keypoint's
    cells (:func:`kpstudy.models.pooling.build_cell_pool`) by one linear layer, whose bias raises
    each target cell so that the seed image ``x0`` has margin ``seed_margin`` in every
    group. Input ``(B, 1, 6, 6)``, output ``(B, 9 + 15)``."""

    def __init__(self, seed: int, x0: torch.Tensor, seed_margin: float = 0.05) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.c1 = nn.Conv2d(1, 3, 3, padding=1)
        self.c2 = nn.Conv2d(3, 2, 3, padding=1)
        made = [
            build_cell_pool(c, d, (SIDE, SIDE)) for c, d in (((1, 2), (1, 1)), ((4, 3), (0, 1)))
        ]
        eye = torch.eye(SIDE * SIDE).reshape(-1, 1, SIDE, SIDE)
        with torch.no_grad():
            mats = [pool(eye).flatten(1).T for pool, _ in made]  # (cells, H·W) each
        sizes = [len(m) for m in mats]
        self.spec = ArgmaxSpec(sizes, [t for _, t in made])
        self.pool = nn.Linear(2 * SIDE * SIDE, sum(sizes))
        with torch.no_grad():
            self.pool.weight.copy_(torch.block_diag(*mats))
            self.pool.bias.zero_()
            y0 = self(x0)[0]
            for k, (start, stop) in enumerate(zip(self.spec.offsets[:-1], self.spec.offsets[1:])):
                group = y0[start:stop]
                target = self.spec.targets[k]
                others = torch.cat([group[:target], group[target + 1 :]])
                self.pool.bias[start + target] = others.max() - group[target] + seed_margin
        self.eval()

    def forward(self, x):
        return self.pool(self.c2(torch.relu(self.c1(x))).flatten(1))


def make_instance(i: int):
    """Instance ``i``: n = 1 + i mod 4, spread 0.05 / 0.2 / 0.5 by i mod 3."""
    n, spread = 1 + i % 4, (0.05, 0.2, 0.5)[i % 3]
    g = torch.Generator().manual_seed(i)
    x0 = torch.randn(1, 1, SIDE, SIDE, generator=g)
    hull = ConvexHull(
        x0 + spread * torch.cat([torch.zeros_like(x0), torch.randn(n, *x0.shape[1:], generator=g)])
    )
    return TinyProxy(i, x0), hull
