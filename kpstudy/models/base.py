"""The common shape of heatmap backbones: a sequence of layers with a checked input."""

from __future__ import annotations

import torch
from torch import nn
from torch.fx._symbolic_trace import is_fx_symbolic_tracing


class HeatmapBackbone(nn.Sequential):
    """``(B, 3, input_size, input_size)`` images → ``(B, K, heatmap_size, heatmap_size)``
    unnormalised heatmaps. ``forward`` names a wrong input shape or dtype (the check is
    skipped while tracing for the verifier or an ONNX export).

    In eval mode without gradients a CPU batch runs :data:`CPU_CHUNK` images at a time:
    a whole batch's activations outgrow the caches, and the study's CNNs run a batch of
    66 images (a hull's witnesses) two to three times faster by sixteen than at once."""

    input_size: int
    heatmap_size: int
    #: Images per pass of a CPU inference batch.
    CPU_CHUNK = 16

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        tracing = is_fx_symbolic_tracing() or torch.jit.is_tracing()
        if not (tracing or torch.compiler.is_compiling()):
            s = self.input_size
            if not isinstance(x, torch.Tensor) or x.ndim != 4 or tuple(x.shape[1:]) != (3, s, s):
                got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
                raise ValueError(f"x: expected images of shape (B, 3, {s}, {s}), got {got}")
            if not x.is_floating_point():
                raise ValueError(f"x: expected a floating-point tensor in [0, 1], got {x.dtype}")
            chunked = not (self.training or torch.is_grad_enabled()) and x.device.type == "cpu"
            if chunked and len(x) > self.CPU_CHUNK:
                run = super().forward
                return torch.cat([run(part) for part in x.split(self.CPU_CHUNK)])
        return super().forward(x)
