"""The operators of a traced graph as maps; every operator's bound rules are in
:mod:`kpstudy.verify.operators`, chosen by the operator's :attr:`Op.kind`.

Affine operators (kind ``'affine'``: convolutions, linear, batch norm in eval, average
pools, the proxy's cell pool, flatten, add, concatenation, channel slicing) give three
maps, from which every bound method derives:

* ``forward(*xs)`` — the concrete operator (with its bias);
* ``linear(*xs)`` — its homogeneous part (no bias), used for coefficient stacks and,
  through autograd's vector–Jacobian product, for backward (CROWN) propagation;
* ``abs_linear(*xs)`` — the same map with absolute weights, so that a lower/upper pair
  ``mid ± rad`` goes to ``linear(mid) + bias ± abs_linear(rad)`` — that is
  ``W⁺L + W⁻U + b`` and ``W⁺U + W⁻L + b``, sound for every affine function in between.

Nonlinear operators (ReLU, max pooling) give ``forward`` only. All maps act on a leading
batch dimension that the bound engine uses for (node, coefficient) pairs, so no operator
may mix the batch.
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from kpstudy.verify import symbols


class Op:
    """A graph operator. ``kind`` names its bound rules in
    :data:`kpstudy.verify.operators.RULES` (``'affine'``, ``'relu'``, ``'maxpool'``).

    An affine operator also says how a zonotope's error symbols, held in spatial blocks
    (:mod:`kpstudy.verify.symbols`), go through it: :attr:`local` and
    :meth:`map_window`, or :meth:`read_blocks`; by default it reads the dense stack."""

    kind = "affine"
    n_inputs = 1
    #: Whether ``linear`` maps each symbol's window of a ``(C, H, W)`` input to a window
    #: of the output: by :meth:`map_window`, or for several inputs by ``linear`` of the
    #: inputs' windows placed on their union.
    local = False

    def forward(self, *xs):
        raise NotImplementedError

    def linear(self, *xs):
        return self.forward(*xs)

    def abs_linear(self, *xs):
        return self.linear(*xs)

    def map_window(self, x, y, x0, out_hw):
        """``linear`` of windows ``x (N, C, h, w)`` at corners ``y, x0 (N,)`` of a local
        one-input operator: the output windows, inside an ``out_hw`` map, and their
        corners. By default each window maps on its own, at its corner (a per-channel
        map, a channel slice)."""
        return self.linear(x), y, x0

    def read_blocks(self, mid, blocks, rows):
        """The dense stack ``(B, rows, *S_out)`` of ``linear`` of a value held as ``θ``
        rows ``mid`` and symbol ``blocks``, for an operator that reads the blocks itself;
        None (the default) where it reads the value's dense stack."""
        return None

    def output_channels(self, channels: torch.Tensor) -> Op | None:
        """The operator computing its output channels ``channels`` (indices) alone, or
        None where it cannot (the default)."""
        return None

    def to(self, dtype) -> Op:
        return self


class _Weighted(Op):
    """A module ``m`` whose homogeneous part is ``_map(x, m.weight)`` (no bias)."""

    def __init__(self, m: nn.Module):
        if getattr(m, "padding_mode", "zeros") != "zeros":
            raise ValueError(
                f"model: {type(m).__name__} padding_mode {m.padding_mode!r} is not supported"
            )
        self.m = m

    def _map(self, x, w):
        raise NotImplementedError

    def forward(self, x):
        return self.m(x)

    def linear(self, x):
        return self._map(x, self.m.weight)

    def abs_linear(self, x):
        return self._map(x, self.m.weight.abs())


class Conv(_Weighted):
    local = True

    def _map(self, x, w):
        m = self.m
        return F.conv2d(x, w, None, m.stride, m.padding, m.dilation, m.groups)

    def map_window(self, x, y, x0, out_hw):
        return symbols.conv_windows(self.m, x, y, x0, out_hw)

    def output_channels(self, channels):
        return _channels(self, channels, 0, _ConvChannels)


class ConvTranspose(_Weighted):
    local = True

    def _map(self, x, w):
        m = self.m
        return F.conv_transpose2d(
            x, w, None, m.stride, m.padding, m.output_padding, m.groups, m.dilation
        )

    def map_window(self, x, y, x0, out_hw):
        return symbols.conv_transpose_windows(self.m, x, y, x0, out_hw)

    def output_channels(self, channels):
        return _channels(self, channels, 1, _ConvTransposeChannels)


def _channels(op: Conv | ConvTranspose, channels: torch.Tensor, dim: int, cls) -> Op | None:
    """``op``'s output channels ``channels`` alone (its weight's ``dim``): a ``cls``
    holding only their weights, whose :meth:`forward` is ``op``'s own sliced (biases stay
    exact); None where ``op`` has groups."""
    m = op.m
    if m.groups != 1:
        return None
    module = copy.copy(m)  # the same geometry, its own weight, no bias
    weight = m.weight.detach()[(slice(None),) * dim + (channels,)]
    module._parameters = {"weight": nn.Parameter(weight, requires_grad=False), "bias": None}
    module.out_channels = len(channels)
    return cls(module, op, channels)


class _Channels:
    def __init__(self, m: nn.Module, source: Op, channels: torch.Tensor):
        super().__init__(m)
        self.source, self.channels = source, channels

    def forward(self, x):
        return self.source.forward(x)[:, self.channels]


class _ConvChannels(_Channels, Conv):
    pass


class _ConvTransposeChannels(_Channels, ConvTranspose):
    pass


class PatchConvTranspose(ConvTranspose):
    """A transposed convolution whose kernel is its stride ``s`` (no padding), with a bias
    ``(C_out, s, s)`` that repeats over the output's ``s × s`` patches: what a chain of
    such layers composes into (:func:`kpstudy.verify.graph.trace` fuses them), each input
    position mapped to its own output patch.

    Parameters
    ----------
    weight : Tensor, shape (C_in, C_out, s, s)
    bias : Tensor, shape (C_out, s, s)
    """

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor):
        c_in, c_out, s, _ = weight.shape
        m = nn.ConvTranspose2d(c_in, c_out, s, s, bias=False).to(weight.dtype)
        with torch.no_grad():
            m.weight.copy_(weight)
        super().__init__(m.eval().requires_grad_(False))
        self.bias = bias

    def forward(self, x):
        h, w = x.shape[-2:]
        return self.m(x) + self.bias.to(x.dtype).repeat(1, h, w)


class FilteredPatchConvTranspose(ConvTranspose):
    """A patch-local transposed convolution (kernel = stride ``s``, e.g. a
    :class:`PatchConvTranspose`) followed by a per-channel convolution of stride 1
    (``k × k``, zero padding ``p``, one filter per channel): the same affine map, its linear
    part one transposed convolution of kernel ``s + k − 1``, stride ``s`` and padding
    ``k − 1 − p``, whose patches overlap by ``k − 1``.

    The bias stays the pair's (:meth:`forward` runs both), since the filter's zero padding
    makes it vary near the border.

    Parameters
    ----------
    patch : ConvTranspose
        Weight ``(C_in, C, s, s)``.
    filter : Conv
        Weight ``(C, 1, k, k)``, ``groups = C``.
    """

    def __init__(self, patch: ConvTranspose, filter: Conv):
        W, f = patch.m.weight.detach().double(), filter.m.weight.detach().double()
        c_in, c, s, _ = W.shape
        k, p = f.shape[-1], filter.m.padding[0]
        weight = W.new_zeros(c_in, c, s + k - 1, s + k - 1)
        for ty in range(k):
            for tx in range(k):
                y, x = k - 1 - ty, k - 1 - tx
                weight[:, :, y : y + s, x : x + s] += W * f[:, 0, ty, tx][None, :, None, None]
        dtype = patch.m.weight.dtype
        m = nn.ConvTranspose2d(c_in, c, s + k - 1, s, k - 1 - p, bias=False).to(dtype)
        with torch.no_grad():
            m.weight.copy_(weight)
        super().__init__(m.eval().requires_grad_(False))
        self.patch, self.filter = patch, filter

    def forward(self, x):
        return self.filter.forward(self.patch.forward(x))


class Dense(_Weighted):
    def _map(self, x, w):
        return F.linear(x, w)


class BatchNorm(Op):
    """Eval-mode batch norm: the per-channel affine map ``x·s + (β − μ s)``."""

    local = True

    def __init__(self, m: nn.BatchNorm2d):
        if m.training or m.running_mean is None:
            raise ValueError(
                "model: BatchNorm2d needs eval mode and running statistics (call model.eval())"
            )
        self.m = m

    def _scale(self, x):
        m = self.m
        s = torch.rsqrt(m.running_var + m.eps)
        if m.weight is not None:
            s = s * m.weight
        return s.to(x.dtype).reshape(-1, 1, 1)

    def forward(self, x):
        return self.m(x)

    def linear(self, x):
        return x * self._scale(x)

    def abs_linear(self, x):
        return x * self._scale(x).abs()


class Pool(Op):
    """``nn.AvgPool2d``: linear, weights >= 0."""

    def __init__(self, m: nn.Module):
        self.m = m

    def forward(self, x):
        return self.m(x)


def cell_pool(x: torch.Tensor, pad, kernel_size, scale: torch.Tensor) -> torch.Tensor:
    """Average of each ``k_v × k_h`` cell of the zero-padded map, times its ``scale``.

    The proxy's cell pool (:class:`kpstudy.models.pooling.CellAvgPool2d` calls it; the tracer
    records a call as one :class:`CellPool` node): linear, weights >= 0.

    Parameters
    ----------
    x : Tensor, shape (B, C, H, W) or (B, H, W)
    pad : (int, int, int, int)
        ``(left, right, top, bottom)`` zeros, as :func:`torch.nn.functional.pad` takes it;
        the padded map is a whole number of cells.
    kernel_size : (int, int)
        ``(k_v, k_h)``, the cell and its stride.
    scale : Tensor, shape (n_v, n_h)
        Per cell (``kernel area / real pixels`` for the proxy); cast to ``x``'s dtype.

    Returns
    -------
    Tensor, shape (B, C, n_v, n_h) or (B, n_v, n_h)
    """
    y = F.avg_pool2d(F.pad(x, pad, value=0.0), kernel_size)  # value: an explicit ONNX Pad input
    return y * scale.to(y.dtype)


class CellPool(Op):
    """:func:`cell_pool` with fixed ``pad``, ``kernel_size``, ``scale (n_v, n_h)``."""

    def __init__(self, pad, kernel_size, scale: torch.Tensor):
        self.pad, self.kernel_size, self.scale = tuple(pad), tuple(kernel_size), scale
        self.n_v, self.n_h = scale.shape

    def forward(self, x):
        return cell_pool(x, self.pad, self.kernel_size, self.scale)

    def read_blocks(self, mid, blocks, rows):
        return symbols.cell_pool(self, mid, blocks, rows)  # each window pooled on its own


class Flatten(Op):
    def __init__(self, start_dim: int, end_dim: int):
        self.start_dim, self.end_dim = start_dim, end_dim

    def forward(self, x):
        return x.flatten(self.start_dim, self.end_dim)


class Add(Op):
    n_inputs = 2
    local = True

    def forward(self, x, y):
        return x + y


class Cat(Op):
    def __init__(self, n_inputs: int, dim: int):
        self.n_inputs, self.dim = n_inputs, dim

    @property
    def local(self) -> bool:  # a channel concatenation
        return self.dim in (1, -3)

    def forward(self, *xs):
        return torch.cat(xs, self.dim)


class Slice(Op):
    def __init__(self, index: tuple):
        self.index = index

    @property
    def local(self) -> bool:  # channels only
        idx = self.index
        return (len(idx) < 2 or isinstance(idx[1], slice)) and all(
            i == slice(None) for i in idx[2:]
        )

    def forward(self, x):
        return x[self.index]


class Identity(Op):
    local = True

    def forward(self, x):
        return x


class ReLU(Op):
    kind = "relu"

    def forward(self, x):
        return torch.relu(x)


class MaxPool(Op):
    """``nn.MaxPool2d`` (no dilation, no ceil mode): ``kernel``, ``stride``, ``padding``
    as ``(h, w)`` pairs."""

    kind = "maxpool"
    local = True  # its rule maps symbol blocks itself (kpstudy.verify.operators)

    def __init__(self, m: nn.MaxPool2d):
        pair = lambda v: (v, v) if isinstance(v, int) else tuple(v)  # noqa: E731
        if pair(m.dilation) != (1, 1) or m.ceil_mode or m.return_indices:
            raise ValueError("model: MaxPool2d with dilation, ceil_mode or return_indices")
        self.m = m
        self.kernel, self.stride, self.padding = (
            pair(m.kernel_size),
            pair(m.stride or m.kernel_size),
            pair(m.padding),
        )

    def forward(self, x):
        return self.m(x)

    def map_window(self, x, y, x0, out_hw):
        """Max pooling of windows (``kpstudy.verify.symbols.pool_windows()``): what a
        symbol's window reaches through the pooling, for its footprint; the zonotope's
        rule maps the coefficients itself (``kpstudy.verify.operators``)."""
        return symbols.pool_windows(self, x, y, x0, out_hw)
