"""kpstudy.models.cnn: the verification-friendly CNNs' decoders."""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models import build_backbone
from kpstudy.verify.graph import trace


def test_the_affine_decoder_cnn_has_the_cnns_parameters_and_relus_only_in_the_encoder():
    natural, affine = build_backbone("cnn"), build_backbone("cnn_affine")
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(natural) == count(affine) and 6.5e5 < count(affine) < 6.7e5
    assert _relus_only_in_the_encoder(affine.eval())
    assert affine(torch.zeros(2, 3, 64, 64)).shape == (2, 23, 64, 64)


def _relus_only_in_the_encoder(net) -> bool:
    kinds = [n.op.kind for n in trace(net, torch.zeros(1, 3, 64, 64)).nodes[1:]]
    last_relu = max(i for i, k in enumerate(kinds) if k == "relu")
    return kinds.count("relu") == 5 and set(kinds[last_relu + 1 :]) == {"affine"}


def test_the_patch_decoder_maps_each_encoder_position_to_its_own_4x4_patch():
    net = build_backbone("cnn_patch").eval()
    assert 3.5e5 < sum(p.numel() for p in net.parameters()) < 3.7e5
    assert _relus_only_in_the_encoder(net)
    modules = list(net.children())
    last = max(i for i, m in enumerate(modules) if isinstance(m, nn.ReLU))
    decoder = nn.Sequential(*modules[last + 1 :])
    features = torch.zeros(1, 128, 16, 16)
    with torch.no_grad():
        base = decoder(features)
        features[0, 7, 5, 9] = 1.0
        moved = (decoder(features) - base).abs().sum(1)[0] > 0  # (64, 64)
    assert moved[20:24, 36:40].all() and moved.sum() == 16
