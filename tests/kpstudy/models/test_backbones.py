"""Backbones, target heads, the keypoint proxy and their ONNX export."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch
from torch import nn

from kpstudy.models import (
    TargetModel,
    argmax_keypoints,
    build_backbone,
    build_proxy,
    dsnt_keypoints,
)
from kpstudy.models.pooling import keypoint_pooling
from kpstudy.verify import export_onnx
from kpstudy.verify.graph import trace


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


def test_a_large_inference_batch_runs_in_chunks_with_the_same_heatmaps(monkeypatch):
    """Without gradients in eval mode a CPU batch goes ``CPU_CHUNK`` images at a time; the
    heatmaps are those of one pass, and a training pass is one pass."""
    from torch import nn

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


def test_resnet18_traces_for_the_verifier_with_its_residual_additions():
    net = build_backbone("resnet18", num_keypoints=4).eval()
    x = torch.rand(1, 3, 256, 256)
    graph = trace(net, x)
    with torch.no_grad():
        torch.testing.assert_close(graph.forward(x), net(x), rtol=1e-4, atol=1e-4)
    assert sum(type(m).__name__ == "MaxPool2d" for m in net.modules()) == 1


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


def _gaussian(centers, size, sigma=1.0, log=False) -> torch.Tensor:
    """Heatmaps ``(1, K, H, W)``: a Gaussian at each ``(u, v)`` (probabilities or logits)."""
    H, W = size
    u, v = torch.meshgrid(torch.arange(W), torch.arange(H), indexing="xy")
    d2 = torch.stack([(u - cu) ** 2 + (v - cv) ** 2 for cu, cv in centers]).double()
    logits = -d2 / (2 * sigma**2)
    return (logits if log else logits.exp())[None]


CENTERS = [(10, 20), (52, 47), (40, 12), (20, 50), (31, 31)]  # all neighbour cells full
DV = [(2, 1), (3, 0), (1, 4), (2, 2), (0, 0)]


def _winner(proxy, heat) -> list[int]:
    y = proxy(heat)[0]
    cells = proxy.index_map
    return [int(y[cells[:, 0] == k].argmax()) for k in range(len(proxy.pools))]


def test_proxy_index_map_and_targets():
    proxy = build_proxy(
        nn.Identity(), keypoint_pooling(CENTERS, DV, (64, 64)), CENTERS, heatmap_size=(64, 64)
    )
    sizes = [p.n_v * p.n_h for p in proxy.pools]
    assert proxy.index_map.shape == (sum(sizes), 2)
    for k, n in enumerate(sizes):
        assert proxy.index_map[proxy.index_map[:, 0] == k, 1].tolist() == list(range(n))
    assert proxy.spec.n_outputs == sum(sizes)
    assert _winner(proxy, _gaussian(CENTERS, (64, 64))) == proxy.target_cells


@pytest.mark.parametrize("log", [False, True])
def test_proxy_argmax_stays_in_the_target_cell_up_to_dv_and_leaves_beyond(log):
    """An ideal Gaussian heatmap moved by (du, dv): the proxy's winning cell is the target
    cell exactly while |du| ≤ δu and |dv| ≤ δv (paper §5.3)."""
    size = (64, 64)
    proxy = build_proxy(
        nn.Identity(), keypoint_pooling(CENTERS, DV, size), CENTERS, heatmap_size=size
    )
    for k, ((cu, cv), (du_max, dv_max)) in enumerate(zip(CENTERS, DV)):
        for du in range(-du_max - 1, du_max + 2):
            for dv in range(-dv_max - 1, dv_max + 2):
                u, v = cu + du, cv + dv
                if not (0 <= u < 64 and 0 <= v < 64):
                    continue
                moved = list(CENTERS)
                moved[k] = (u, v)
                won = _winner(proxy, _gaussian(moved, size, log=log))[k]
                inside = abs(du) <= du_max and abs(dv) <= dv_max
                assert (won == proxy.target_cells[k]) == inside, (k, du, dv)


def test_partial_border_cells_are_where_proxy_and_argmax_part():
    """The limit of the property above. A border cell averages its real pixels only:
    - probabilities: a 1-pixel cell next to a peak at the edge of its 9-pixel target cell
      has the larger average, although the peak is inside the target cell;
    - logits: a 4-pixel target cell [0, 3] keeps winning when the peak has moved to 4,
      outside it (the mean of −d²/2 over d = 1..4 beats that over d = 0..6).
    A proxy certificate speaks of cell averages; near the heatmap border it does not bound
    the heatmap's argmax (kpstudy.certify.allocation_method checks the target model end to end)."""
    proxy = build_proxy(
        nn.Identity(),
        keypoint_pooling([(40, 5)], [(1, 4)], (64, 64)),
        [(40, 5)],
        heatmap_size=(64, 64),
    )
    assert proxy.pools[0].n_v == 8  # rows [-8, 0] (one real pixel), [1, 9], ...
    assert _winner(proxy, _gaussian([(40, 2)], (64, 64)))[0] == proxy.target_cells[0]
    assert _winner(proxy, _gaussian([(40, 1)], (64, 64)))[0] != proxy.target_cells[0]

    proxy = build_proxy(
        nn.Identity(),
        keypoint_pooling([(0, 30)], [(3, 0)], (64, 64)),
        [(0, 30)],
        heatmap_size=(64, 64),
    )
    assert _winner(proxy, _gaussian([(4, 30)], (64, 64), log=True))[0] == proxy.target_cells[0]
    assert _winner(proxy, _gaussian([(4, 30)], (64, 64)))[0] != proxy.target_cells[0]


def test_proxy_spec_leaves_out_unverified_keypoints_and_traces():
    proxy = build_proxy(
        nn.Identity(),
        keypoint_pooling(CENTERS[:3], DV[:3], (64, 64)),
        CENTERS[:3],
        heatmap_size=(64, 64),
        verified=[True, False, True],
    )
    heat = _gaussian(CENTERS[:3], (64, 64)).float()
    assert proxy.spec.targets[1] is None
    assert (proxy.spec.margins(proxy(heat)) > 0).all()
    torch.testing.assert_close(trace(proxy, heat).forward(heat), proxy(heat))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(centers=[(1, 1)]), r"centers: expected \(2, 2\) integer"),
        (dict(centers=[(1, 1), (9, 1)]), r"centers\[1\]: expected a pixel inside"),
        (dict(heatmap_size=None), "heatmap_size: expected"),
        (dict(verified=[True]), "verified: expected 2 entries"),
    ],
)
def test_proxy_bad_input_is_named(kwargs, message):
    pooling = keypoint_pooling([(1, 1), (2, 2)], [(1, 1), (0, 0)], (8, 8))
    args = dict(centers=[(1, 1), (2, 2)], heatmap_size=(8, 8)) | kwargs
    with pytest.raises(ValueError, match=message):
        build_proxy(nn.Identity(), pooling, **args)
    with pytest.raises(ValueError, match="dv: expected 2 rows"):
        keypoint_pooling([(1, 1), (2, 2)], [(1, 1)], (8, 8))


def test_dsnt_and_argmax_agree_on_symmetric_heatmaps():
    """Paper Proposition 1: symmetric marginals → the softmax's mean is its mode."""
    centers = [(20, 30), (33, 17), (45, 44)]
    for sigma in (0.7, 1.5, 3.0):
        logits = _gaussian(centers, (64, 64), sigma, log=True)
        np.testing.assert_allclose(dsnt_keypoints(logits)[0].numpy(), centers, atol=1e-6)
        assert argmax_keypoints(logits)[0].tolist() == [list(c) for c in centers]


def test_dsnt_and_argmax_disagree_on_a_skewed_heatmap():
    """A peak at (20, 30) with a long tail to the right: the argmax stays on the peak,
    the mean moves right by more than a pixel."""
    logits = _gaussian([(20, 30)], (64, 64), 1.0, log=True)
    u = torch.arange(64).double()
    tail = torch.where(u > 20, -0.5 - 0.08 * (u - 20), torch.tensor(-1e9).double())
    logits = torch.maximum(
        logits, tail.expand(64, 64) - 0.5 * (torch.arange(64)[:, None] - 30) ** 2
    )
    assert argmax_keypoints(logits)[0, 0].tolist() == [20, 30]
    mean = dsnt_keypoints(logits)[0, 0]
    assert mean[0] > 21.5 and abs(mean[1] - 30) < 1e-6


def test_target_model_heads():
    net = build_backbone("cnn", 3).eval()
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        h = net(x)
        torch.testing.assert_close(TargetModel(net, "dsnt")(x), dsnt_keypoints(h))
        assert torch.equal(TargetModel(net, "argmax")(x), argmax_keypoints(h))
    with pytest.raises(ValueError, match="head: expected one of"):
        TargetModel(net, "mean")


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
