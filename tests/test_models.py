"""The paper-sized CNN backbone and the keypoint proxy builder."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.models import HeatmapCNN, build_proxy
from kpstudy.verify.graph import trace


def test_cnn_shape_and_size_match_the_paper():
    net = HeatmapCNN(23).eval()
    with torch.no_grad():
        assert net(torch.zeros(2, 3, 64, 64)).shape == (2, 23, 64, 64)
    n = sum(p.numel() for p in net.parameters())
    assert 6.3e5 < n < 6.9e5  # paper: 6.57e5


def test_proxy_target_is_the_peak_cell_and_the_graph_traces():
    H, W = 20, 24
    centers = [(3, 4), (20, 17), (11, 0)]
    dv = [(1, 1), (2, 0), (0, 3)]
    u, v = torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy")
    heat = torch.stack([-((u - cu) ** 2 + (v - cv) ** 2).float() for cu, cv in centers])[None]
    proxy, spec = build_proxy(nn.Identity(), centers, dv, (H, W), verified=[True, True, False])
    y = proxy(heat)
    assert y.shape == (1, spec.n_outputs)
    assert (spec.margins(y) > 0).all()
    assert spec.targets[2] is None
    graph = trace(proxy, heat)
    torch.testing.assert_close(graph.forward(heat), y)


def test_proxy_bad_input_is_named():
    with pytest.raises(ValueError, match="dv: expected 2 rows"):
        build_proxy(nn.Identity(), [(1, 1), (2, 2)], [(1, 1)], (8, 8))
