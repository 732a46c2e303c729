"""Heatmaps made by hand for the model tests."""

from __future__ import annotations

import torch


def gaussian_heatmaps(centers, size, sigma=1.0, log=False) -> torch.Tensor:
    """Heatmaps ``(1, K, H, W)``: a Gaussian at each ``(u, v)`` (probabilities or logits)."""
    H, W = size
    u, v = torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy")
    d2 = torch.stack([(u - cu) ** 2 + (v - cv) ** 2 for cu, cv in centers]).double()
    logits = -d2 / (2 * sigma**2)
    return (logits if log else logits.exp())[None]
