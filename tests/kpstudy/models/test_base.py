"""kpstudy.models.base: the common backbone's chunked CPU inference."""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models import build_backbone


def test_a_large_inference_batch_runs_in_chunks_with_the_same_heatmaps(monkeypatch):
    """Without gradients in eval mode a CPU batch goes ``CPU_CHUNK`` images at a time; the
    heatmaps are those of one pass, and a training pass is one pass."""

    torch.manual_seed(0)
    net = build_backbone("cnn_patch_smooth", 3).double().eval()
    x = torch.rand(2 * net.CPU_CHUNK + 3, 3, 64, 64, dtype=torch.float64)
    passes = []
    monkeypatch.setattr(nn.Sequential, "forward", lambda self, x: passes.append(len(x)) or x[:, :3])
    with torch.no_grad():
        net(x)
    assert passes == [net.CPU_CHUNK, net.CPU_CHUNK, 3]
    passes.clear()
    net.train()
    net(x)
    assert passes == [len(x)]
    monkeypatch.undo()
    net.eval()
    with torch.no_grad():
        chunked = net(x)
        whole = nn.Sequential.forward(net, x)
    torch.testing.assert_close(chunked, whole, rtol=1e-12, atol=1e-12)
