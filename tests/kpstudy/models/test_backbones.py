"""kpstudy.models.backbones: the backbones' sizes and shapes, their refusals, and their
ONNX export (backbone, proxy, ResNet-18) against torch."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch
from torch import nn

from kpstudy.models import build_backbone, build_proxy
from kpstudy.models.pooling import keypoint_pooling
from kpstudy.verify import export_onnx


def _params(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


@pytest.mark.parametrize(
    "name, size, low, high",
    [("cnn", 64, 0.9 * 6.57e5, 1.1 * 6.57e5), ("resnet18", 256, 0.9 * 1.2e7, 1.1 * 1.2e7)],
)
def test_backbone_sizes_and_shapes_match_the_paper(name, size, low, high):
    net = build_backbone(name).eval()
    assert (net.input_size, net.heatmap_size) == (size, size)
    assert low < _params(net) < high
    with torch.no_grad():
        assert net(torch.zeros(2, 3, size, size)).shape == (2, 23, size, size)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: build_backbone("vgg"), "name: expected one of"),
        (lambda: build_backbone("cnn", 0), "num_keypoints: expected a positive integer"),
        (
            lambda: build_backbone("cnn")(torch.zeros(1, 1, 64, 64)),
            r"x: expected images of shape \(B, 3, 64, 64\)",
        ),
        (lambda: build_backbone("cnn")(torch.zeros(1, 3, 32, 32)), r"got \(1, 3, 32, 32\)"),
        (
            lambda: build_backbone("cnn")(torch.zeros(1, 3, 64, 64, dtype=torch.uint8)),
            "floating-point",
        ),
    ],
)
def test_backbone_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize("which", ["backbone", "proxy", "resnet18"])
def test_onnx_export_matches_torch(tmp_path, which):
    torch.manual_seed(0)
    net = build_backbone("resnet18" if which == "resnet18" else "cnn").eval()
    x = torch.rand(1, 3, net.input_size, net.input_size)
    if which == "proxy":
        centers = [(5 + 2 * k, 60 - 2 * k) for k in range(23)]
        net = build_proxy(
            net,
            keypoint_pooling(centers, [(k % 4, 3 - k % 4) for k in range(23)], (64, 64)),
            centers,
        )
    path = export_onnx(net, x, tmp_path / f"{which}.onnx")
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (y,) = session.run(None, {"x": x.numpy()})
    with torch.no_grad():
        expected = net(x).numpy()
    assert y.shape == expected.shape
    assert np.abs(y - expected).max() <= 1e-4
