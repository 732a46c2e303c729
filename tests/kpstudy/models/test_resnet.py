"""kpstudy.models.resnet: ResNet-18 as the verifier traces it."""

from __future__ import annotations

import torch

from kpstudy.models import build_backbone
from kpstudy.verify.graph import trace


def test_resnet18_traces_for_the_verifier_with_its_residual_additions():
    net = build_backbone("resnet18", num_keypoints=4).eval()
    x = torch.rand(1, 3, 256, 256)
    graph = trace(net, x)
    with torch.no_grad():
        torch.testing.assert_close(graph.forward(x), net(x), rtol=1e-4, atol=1e-4)
    assert sum(type(m).__name__ == "MaxPool2d" for m in net.modules()) == 1
