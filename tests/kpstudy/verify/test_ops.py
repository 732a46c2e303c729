"""kpstudy.verify.ops: every affine operator is ``linear`` plus its value at zero, and
``abs_linear`` bounds ``|linear|`` (``W⁺L + W⁻U`` stays sound); a fused patch map is the
pair it replaces; an operator narrowed to some output channels computes those channels."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.verify import ops


def _seeded(module):
    torch.manual_seed(0)
    for p in module.parameters():
        nn.init.uniform_(p, -1.0, 1.0)
    return module.double().eval()


def _batch_norm():
    bn = _seeded(nn.BatchNorm2d(3))
    with torch.no_grad():
        bn.running_mean.uniform_(-1, 1)
        bn.running_var.uniform_(0.5, 2)
    return ops.BatchNorm(bn)


AFFINE = {
    "conv": (lambda: ops.Conv(_seeded(nn.Conv2d(3, 4, 3, stride=2, padding=1))), [(3, 8, 8)]),
    "conv_transpose": (
        lambda: ops.ConvTranspose(_seeded(nn.ConvTranspose2d(3, 3, 3, stride=2, padding=1))),
        [(3, 5, 5)],
    ),
    "dense": (lambda: ops.Dense(_seeded(nn.Linear(6, 4))), [(6,)]),
    "batch_norm": (_batch_norm, [(3, 4, 4)]),
    "pool": (lambda: ops.Pool(nn.AvgPool2d(2)), [(3, 4, 4)]),
    "cell_pool": (lambda: ops.CellPool((1, 0, 0, 2), (2, 3), torch.rand(3, 3) + 0.5), [(1, 4, 8)]),
    "flatten": (lambda: ops.Flatten(1, -1), [(2, 3, 3)]),
    "add": (lambda: ops.Add(), [(2, 3, 3), (2, 3, 3)]),
    "cat": (lambda: ops.Cat(2, 1), [(2, 3, 3), (1, 3, 3)]),
    "slice": (lambda: ops.Slice((slice(None), slice(1, 3))), [(4, 3, 3)]),
    "identity": (lambda: ops.Identity(), [(2, 3)]),
}


@pytest.mark.parametrize("name", AFFINE)
def test_an_affine_operator_is_its_linear_part_plus_its_value_at_zero(name):
    make, shapes = AFFINE[name]
    op = make()
    g = torch.Generator().manual_seed(1)
    xs = [torch.randn(5, *s, generator=g, dtype=torch.float64) for s in shapes]
    zeros = [torch.zeros(1, *s, dtype=torch.float64) for s in shapes]
    with torch.no_grad():
        torch.testing.assert_close(op.forward(*xs), op.linear(*xs) + op.forward(*zeros))
        # The radius map: |linear(d)| <= abs_linear(|d|), equal on d >= 0 where the
        # weights are nonnegative.
        assert (op.linear(*xs).abs() <= op.abs_linear(*(x.abs() for x in xs)) + 1e-12).all()
        if name in ("pool", "cell_pool", "add", "cat", "slice", "identity", "flatten"):
            positive = [x.abs() for x in xs]
            torch.testing.assert_close(op.abs_linear(*positive), op.linear(*positive))
    assert op.kind == "affine"


def test_weighted_operators_take_absolute_weights_for_the_radius():
    op = AFFINE["conv"][0]()
    d = torch.randn(2, 3, 8, 8, dtype=torch.float64)
    m = op.m
    want = nn.functional.conv2d(d, m.weight.abs(), None, m.stride, m.padding)
    torch.testing.assert_close(op.abs_linear(d), want)
    bn = _batch_norm()
    e = d[:, :3, :4, :4]
    torch.testing.assert_close(bn.abs_linear(e.abs()), bn.linear(e).abs())


def test_a_patch_map_and_its_filter_are_the_pair_they_replace():
    """A PatchConvTranspose repeats its bias over the patches; a FilteredPatchConvTranspose
    has the patch map and per-channel filter's linear part in one transposed convolution
    (its bias stays the pair's)."""
    torch.manual_seed(2)
    weight = torch.randn(3, 2, 4, 4, dtype=torch.float64)
    bias = torch.randn(2, 4, 4, dtype=torch.float64)
    patch = ops.PatchConvTranspose(weight, bias)
    x = torch.randn(2, 3, 5, 6, dtype=torch.float64)
    y = patch.forward(x)
    assert y.shape == (2, 2, 20, 24)
    torch.testing.assert_close(y - patch.linear(x), bias.repeat(1, 5, 6).expand(2, -1, -1, -1))
    smooth = _seeded(nn.Conv2d(2, 2, 3, padding=1, groups=2))
    fused = ops.FilteredPatchConvTranspose(patch, ops.Conv(smooth))
    assert fused.m.kernel_size == (6, 6) and fused.m.stride == (4, 4)
    torch.testing.assert_close(fused.forward(x), smooth(y))
    filtered = nn.functional.conv2d(patch.linear(x), smooth.weight, None, padding=1, groups=2)
    torch.testing.assert_close(fused.linear(x), filtered)


@pytest.mark.parametrize("kind", ["conv", "conv_transpose"])
def test_an_operator_narrowed_to_some_channels_computes_those_channels(kind):
    op = AFFINE[kind][0]()
    x = torch.randn(3, *AFFINE[kind][1][0], dtype=torch.float64)
    channels = torch.tensor([1, 0])
    narrow = op.output_channels(channels)
    torch.testing.assert_close(narrow.forward(x), op.forward(x)[:, channels])
    torch.testing.assert_close(narrow.linear(x), op.linear(x)[:, channels])
    dim = 0 if kind == "conv" else 1
    assert narrow.m.weight.shape[dim] == 2 < op.m.weight.shape[dim]  # the weights it needs
    grouped = ops.Conv(_seeded(nn.Conv2d(4, 4, 3, groups=2)))
    assert grouped.output_channels(channels) is None


def test_operators_refuse_what_their_bounds_cannot_follow():
    with pytest.raises(ValueError, match="^model: Conv2d padding_mode 'reflect'"):
        ops.Conv(nn.Conv2d(1, 1, 3, padding=1, padding_mode="reflect"))
    with pytest.raises(ValueError, match="^model: BatchNorm2d needs eval mode"):
        ops.BatchNorm(nn.BatchNorm2d(2))
    with pytest.raises(ValueError, match="^model: MaxPool2d with dilation"):
        ops.MaxPool(nn.MaxPool2d(2, ceil_mode=True))
    assert ops.ReLU().kind == "relu" and ops.MaxPool(nn.MaxPool2d(2)).kind == "maxpool"
