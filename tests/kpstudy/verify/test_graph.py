"""kpstudy.verify.graph: tracing a torch model into the verifier's operators."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.verify import ConvexHull, output_bounds
from tests.helpers.verify_nets import MixedNet, PatchNet, hull_vertices


def test_batch_norm_is_folded_into_the_convolution_that_feeds_it():
    from kpstudy.verify.graph import trace

    net = MixedNet(seed=2)
    x = hull_vertices(2, 3, (2, 8, 8))
    graph = trace(net, x[:1])
    names = [n.name for n in graph.nodes]
    assert "conv1+bn" in names
    assert not any(type(n.op).__name__ == "BatchNorm" for n in graph.nodes)
    with torch.no_grad():
        torch.testing.assert_close(graph.forward(x), net(x), rtol=1e-5, atol=1e-5)


def test_a_fusion_that_would_cost_more_is_not_made():
    from kpstudy.verify.graph import trace
    from kpstudy.verify.ops import PatchConvTranspose

    net = PatchNet(0, bottleneck=True).double()
    x = hull_vertices(0, 2, (2, 8, 8), dtype=torch.float64)
    graph = trace(net, x[:1])
    kinds = [type(n.op).__name__ for n in graph.nodes]
    assert kinds.count("ConvTranspose") + kinds.count("PatchConvTranspose") == 2, kinds
    with torch.no_grad():
        torch.testing.assert_close(graph.forward(x), net(x), rtol=1e-12, atol=1e-12)
    assert any(isinstance(n.op, PatchConvTranspose) for n in graph.nodes)  # the cheap pair


def test_unsupported_layer_is_named():
    net = nn.Sequential(nn.Conv2d(1, 2, 3), nn.Sigmoid()).eval()
    with pytest.raises(ValueError, match="model: unsupported operation Sigmoid"):
        output_bounds(net, ConvexHull(torch.randn(2, 1, 5, 5)))

    class Gelu(nn.Module):
        def forward(self, x):
            return torch.nn.functional.gelu(x)

    with pytest.raises(ValueError, match="model: unsupported operation gelu"):
        output_bounds(Gelu(), ConvexHull(torch.randn(2, 1, 5, 5)))


def test_training_mode_batch_norm_is_refused():
    net = nn.Sequential(nn.Conv2d(1, 2, 3), nn.BatchNorm2d(2))
    with pytest.raises(ValueError, match="BatchNorm2d needs eval mode"):
        output_bounds(net, ConvexHull(torch.randn(2, 1, 5, 5)))


def test_every_node_reads_earlier_nodes_and_the_graph_computes_the_model():
    """Node 0 is the input, each node reads earlier ones (``consumers`` the reverse), the
    shapes are the model's, and the graph computes the model through every operator of
    MixedNet (residual add, slicing, concatenation, pools, transposed conv, flatten)."""
    from kpstudy.verify.graph import trace

    net = MixedNet(seed=3).double()
    x = hull_vertices(3, 4, (2, 8, 8), dtype=torch.float64)
    graph = trace(net, x[:1])
    first, *rest = graph.nodes
    assert first.op is None and first.inputs == () and first.shape == (2, 8, 8)
    for i, node in enumerate(rest, start=1):
        assert node.inputs and all(j < i for j in node.inputs), node
        assert all(i in graph.consumers[j] for j in node.inputs)
    assert graph.consumers[-1] == [] and graph.nodes[-1].shape == (6,) and graph.output_size == 6
    kinds = {type(n.op).__name__ for n in rest}
    assert {"Add", "Slice", "Cat", "Pool", "MaxPool", "ConvTranspose", "Flatten", "Dense"} <= kinds
    assert graph.dtype == torch.float64 and not graph.differentiable
    with torch.no_grad():
        torch.testing.assert_close(graph.forward(x), net(x), rtol=1e-12, atol=1e-12)
        for node in graph.nodes:
            if node.offset is not None:  # an affine node's stored forward(0)
                zeros = [torch.zeros(1, *graph.nodes[j].shape).double() for j in node.inputs]
                torch.testing.assert_close(node.offset, node.op.forward(*zeros))


def test_a_differentiable_graph_keeps_the_models_modules_and_their_gradients():
    """Traced ``differentiable``, a batch norm stays its own node, no offset is stored and
    :meth:`Graph.offset` follows the live parameters; gradients reach every parameter.
    The folded graph's stored offsets do not move with the model."""
    from kpstudy.verify.graph import trace

    net = MixedNet(seed=4)
    x = hull_vertices(4, 3, (2, 8, 8))
    live = trace(net, x[:1], differentiable=True)
    folded = trace(net, x[:1])
    assert live.differentiable and "bn" in [n.name for n in live.nodes]
    assert all(n.offset is None for n in live.nodes)
    bn = next(i for i, n in enumerate(live.nodes) if n.name == "bn")
    conv = next(i for i, n in enumerate(folded.nodes) if n.name == "conv1+bn")
    before_live, before_folded = live.offset(bn).detach().clone(), folded.offset(conv).clone()
    with torch.no_grad():
        net.bn.bias += 1.0
    torch.testing.assert_close(live.offset(bn), before_live + 1.0)
    torch.testing.assert_close(folded.offset(conv), before_folded)
    torch.testing.assert_close(live.forward(x), net(x))
    live.forward(x).square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_the_affine_tail_splits_off_after_the_last_relu():
    from kpstudy.verify.graph import trace

    torch.manual_seed(5)
    net = nn.Sequential(
        nn.Conv2d(2, 4, 3, padding=1), nn.ReLU(), nn.Conv2d(4, 4, 3), nn.Conv2d(4, 3, 1)
    ).double()
    x = torch.randn(3, 2, 8, 8, dtype=torch.float64)
    graph = trace(net, x[:1])
    head, tail = graph.split_affine_tail()
    assert type(head.nodes[-1].op).__name__ == "ReLU" and len(tail.nodes) == 3
    assert tail.nodes[0].op is None and tail.nodes[0].shape == head.nodes[-1].shape
    with torch.no_grad():
        torch.testing.assert_close(tail.forward(head.forward(x)), net(x))
        channels = torch.tensor([2, 0])
        narrow = graph.output_channels(channels)
        torch.testing.assert_close(narrow.forward(x), net(x)[:, channels])
    assert narrow.nodes[-1].shape == (2, 6, 6)
    assert trace(nn.Sequential(*net, nn.ReLU()), x[:1]).split_affine_tail() is None
    flat = trace(nn.Sequential(nn.Flatten(), nn.Linear(128, 4)).double(), x[:1])
    assert flat.output_channels(torch.tensor([0])) is None  # not a (C, H, W) convolution


class _Given(nn.Module):
    """A module whose ``forward(x)`` is given: for the refusals below."""

    def __init__(self, forward):
        super().__init__()
        self.conv = nn.Conv2d(2, 2, 3, padding=1)
        self.drop = nn.Dropout(0.5)
        self._forward = forward

    def forward(self, x):
        return self._forward(self, x)


class _TwoInputs(nn.Module):
    def forward(self, x, y):
        return x + y


def _if_positive(m, x):
    return m.conv(x) if x.sum() > 0 else x


@pytest.mark.parametrize(
    "forward, message",
    [
        (lambda m, x: m.drop(m.conv(x)), "^model: Dropout needs eval mode"),
        (lambda m, x: m.conv(x).flatten(0), "^model: flatten over the batch dimension"),
        (lambda m, x: torch.cat([x, x], 0), "^model: cat over the batch dimension"),
        (lambda m, x: m.conv(x)[0], "^model: only slicing that keeps the batch"),
        (lambda m, x: torch.sigmoid(x), "^model: unsupported operation sigmoid"),
        (lambda m, x: x.exp(), r"^model: unsupported operation Tensor.exp"),
        (lambda m, x: (m.conv(x), x), "^model: expected a single output tensor"),
        (_if_positive, "^model: could not be traced with torch.fx"),
        (lambda m, x: [m.conv(x), torch.relu(x)][0], "^model: the output must be the last"),
        (lambda m, x: m.conv(x) + 1.0, r"^model: expected 2 tensor argument\(s\)"),
    ],
)
def test_what_cannot_be_traced_is_refused_by_name(forward, message):
    from kpstudy.verify.graph import trace

    with pytest.raises(ValueError, match=message):
        trace(_Given(forward).train(), torch.zeros(1, 2, 6, 6))


def test_an_input_that_does_not_fit_the_model_or_no_module_is_refused():
    from kpstudy.verify.graph import trace

    with pytest.raises(ValueError, match="^model: expected a single input tensor"):
        trace(_TwoInputs(), torch.zeros(1, 2, 6, 6))
    with pytest.raises(ValueError, match=r"^input_set: images of shape \(3, 6, 6\) do not fit"):
        trace(nn.Sequential(nn.Conv2d(2, 2, 3)), torch.zeros(1, 3, 6, 6))
    with pytest.raises(ValueError, match="^model: expected a torch.nn.Module, got builtin"):
        trace(torch.relu, torch.zeros(1, 2, 6, 6))
