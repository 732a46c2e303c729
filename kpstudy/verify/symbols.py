"""A zonotope's error symbols stored by where they reach (spatial blocks).

A DeepZ error symbol (:mod:`kpstudy.verify.bounds`, method ``'zonotope'``) is made at one
unstable ReLU neuron, and each later convolution widens its reach by one kernel: through
most of a convolutional network a symbol touches a small window of each activation,
while a dense stack ``(B, E, C, H, W)`` pays for the whole activation per symbol. Here
the symbols made in one tile of one ReLU share a :class:`Block`: their coefficients
``(B, r, C, h, w)`` on a window of a ``(C, H, W)`` activation, zero outside it.
Convolutions, transposed convolutions, per-channel maps and channel slices map blocks to
blocks (:func:`apply`), sums and channel concatenations merge them (:func:`combine`);
the proxy's cell pool reads each block into the dense stack of its cells
(:func:`cell_pool`), so the full-resolution dense stack is never formed; any other
operator gets the dense stack (:func:`dense`). Within one value a symbol lives
in one block only, so ``Σ_e |coefficient|`` (:func:`reach`) is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from kpstudy.verify import ops

#: Tiles per side in which one ReLU's new symbols are grouped.
TILES = 4


@dataclass
class Block:
    """Symbols ``[start, start + r)`` (rows of the dense stack) of a ``(C, H, W)`` value:
    coefficients ``coeff (B, r, C, h, w)`` on rows ``y … y + h`` and columns
    ``x … x + w``, zero elsewhere."""

    coeff: torch.Tensor
    start: int
    y: int
    x: int

    @property
    def rows(self) -> int:
        return self.coeff.shape[1]

    def window(self) -> tuple[slice, slice]:
        h, w = self.coeff.shape[-2:]
        return slice(self.y, self.y + h), slice(self.x, self.x + w)


def is_local(op: ops.Op, in_shapes, out_shape) -> bool:
    """Whether ``op`` maps blocks to blocks (see the module docstring)."""
    if len(out_shape) != 3 or any(len(s) != 3 for s in in_shapes):
        return False
    if isinstance(op, (ops.Conv, ops.ConvTranspose, ops.BatchNorm, ops.Identity, ops.Add)):
        return True
    if isinstance(op, ops.Cat):
        return op.dim in (1, -3)
    if isinstance(op, ops.Slice):
        idx = op.index
        return (len(idx) < 2 or isinstance(idx[1], slice)) and all(
            i == slice(None) for i in idx[2:]
        )
    return False


#: Entries per row of :func:`l1_rows`' input up to which one reduction is fastest.
L1_DIRECT = 4096


def l1_rows(x: torch.Tensor, chunk: int = 16) -> torch.Tensor:
    """``Σ_i |x[:, i]|`` for ``x (B, r, …)``. Rows of more than :data:`L1_DIRECT` entries
    go a few at a time (``vector_norm`` and ``abs().sum(1)`` over a middle dimension are
    then 2–14× slower on the CPU); shorter ones, such as a search's margin rows, in one
    reduction (the loop's overhead would be 2–5× its work)."""
    if x[:1, :1].numel() <= L1_DIRECT:
        return x.abs().sum(1)
    parts = x.split(chunk, 1)  # one backward (a concatenation), not one per slice
    out = parts[0].abs().sum(1)
    for part in parts[1:]:
        out += part.abs().sum(1)
    return out


class _Assemble(torch.autograd.Function):
    """``Σ_i zero-padded parts[i]`` placed at ``index[i]`` of a zero tensor; the backward
    reads each part's window of the gradient (in-place slice writes would make autograd
    clone the whole stack once per part)."""

    @staticmethod
    def forward(ctx, shape, index, *parts):
        out = parts[0].new_zeros(shape)
        for where, part in zip(index, parts):
            out[where] += part
        ctx.index = index
        return out

    @staticmethod
    def backward(ctx, grad):
        return (None, None, *(grad[where] for where in ctx.index))


def assemble(shape, like: torch.Tensor, parts) -> torch.Tensor:
    """A tensor of ``shape`` (``like``'s dtype and device), zero but for the sum of each
    ``(index, part)`` of ``parts`` at its ``index`` (a tuple of slices)."""
    if not parts:
        return like.new_zeros(shape)
    index, tensors = zip(*parts)
    return _Assemble.apply(tuple(shape), index, *tensors)


def reach(blocks: list[Block], like: torch.Tensor) -> torch.Tensor:
    """``Σ_e |coefficient of symbol e|`` per entry, ``(B, C, H, W)`` like ``like``."""
    return assemble(
        like.shape,
        like,
        [((slice(None), slice(None), *b.window()), l1_rows(b.coeff)) for b in blocks],
    )


def gather(blocks: list[Block], rows: int, start: int, like: torch.Tensor, index: torch.Tensor):
    """The symbols' coefficients ``(B, rows, n)`` on the flat entries ``index (n,)`` of a
    value held as ``like (B, q, C, H, W)`` and ``blocks``, symbol ``e`` in row
    ``e − start`` (the dense stack's rows past its ``start`` affine ones, without forming
    it); ``rows`` is the number of symbols in all."""
    H, W = like.shape[-2:]
    c, y, x = index // (H * W), index // W % H, index % W
    out = like.new_zeros(like.shape[0], rows, len(index))
    for b in blocks:
        h, w = b.coeff.shape[-2:]
        inside = ((y >= b.y) & (y < b.y + h) & (x >= b.x) & (x < b.x + w)).nonzero().flatten()
        if len(inside) == 0:
            continue
        local = (c[inside] * h + y[inside] - b.y) * w + x[inside] - b.x
        r0 = b.start - start
        out[:, r0 : r0 + b.rows, inside] = b.coeff.flatten(2)[:, :, local]
    return out


def dense(mid: torch.Tensor, blocks: list[Block], rows: int) -> torch.Tensor:
    """The dense stack ``(B, rows, *S)``: ``mid (B, q, *S)`` then every symbol's row."""
    parts = [((slice(None), slice(0, mid.shape[1])), mid)]
    parts += [
        ((slice(None), slice(b.start, b.start + b.rows), slice(None), *b.window()), b.coeff)
        for b in blocks
    ]
    return assemble((mid.shape[0], rows, *mid.shape[2:]), mid, parts)


def cell_pool(op: ops.CellPool, mid: torch.Tensor, blocks: list[Block], rows: int):
    """The dense stack ``(B, rows, 1, n_v, n_h)`` of the cell pool ``op`` of a value held
    as ``θ`` rows ``mid (B, q, 1, H, W)`` and symbol ``blocks``.

    A cell is a ``k_v × k_h`` window of the padded map, so each block is padded to whole
    cells (a few pixels) and pooled on its own; the ``(B, rows, 1, H, W)`` stack that
    :func:`dense` would build and pad is never formed."""
    B, q = mid.shape[:2]
    parts = [
        (
            (slice(None), slice(0, q)),
            op.forward(mid.reshape(B * q, *mid.shape[2:])).reshape(B, q, 1, op.n_v, op.n_h),
        )
    ]
    (kv, kh), (left, _, top, _) = op.kernel_size, op.pad
    scale = op.scale.to(mid.dtype)
    unit = bool((scale == 1).all())
    for b in blocks:
        r, (h, w) = b.rows, b.coeff.shape[-2:]
        y, x = b.y + top, b.x + left  # the window in the padded map
        c0, c1, d0, d1 = y // kv, -(-(y + h) // kv), x // kh, -(-(x + w) // kh)
        pad = (x - d0 * kh, d1 * kh - x - w, y - c0 * kv, c1 * kv - y - h)
        # The stride-1 proxy's one-pixel cells of scale 1 pass as they are.
        pooled = b.coeff.reshape(B * r, 1, h, w)
        if any(pad):
            pooled = F.pad(pooled, pad)
        if (kv, kh) != (1, 1):
            pooled = F.avg_pool2d(pooled, (kv, kh))
        if not unit:
            pooled = pooled * scale[c0:c1, d0:d1]
        window = (
            slice(None),
            slice(b.start, b.start + r),
            slice(None),
            slice(c0, c1),
            slice(d0, d1),
        )
        parts.append((window, pooled.reshape(B, r, 1, c1 - c0, d1 - d0)))
    return assemble((B, rows, 1, op.n_v, op.n_h), mid, parts)


def make(mu: torch.Tensor, start: int) -> list[Block]:
    """New symbols for the nonzero entries of ``mu (B, C, H, W)`` (one each, coefficient
    ``μ``), numbered from ``start``, grouped by tile; a tile's rows are its largest count
    over the batch (shorter regions get zero rows)."""
    B, C, H, W = mu.shape
    th, tw = math.ceil(H / TILES), math.ceil(W / TILES)
    blocks = []
    for y in range(0, H, th):
        for x in range(0, W, tw):
            tile = mu[:, :, y : y + th, x : x + tw]
            nonzero = tile > 0
            r = int(nonzero.flatten(1).sum(1).max())
            if r == 0:
                continue
            rows, cols = nonzero.any(0).any(0).nonzero(as_tuple=True)  # the window
            tile = tile[:, :, rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
            flat = tile.reshape(B, -1)
            order = (flat > 0).to(torch.uint8).argsort(dim=1, descending=True, stable=True)[:, :r]
            coeff = flat.new_zeros(B, r, flat.shape[1])
            coeff.scatter_(2, order[:, :, None], flat.gather(1, order)[:, :, None])
            blocks.append(
                Block(
                    coeff.view(B, r, *tile.shape[1:]),
                    start,
                    y + int(rows.min()),
                    x + int(cols.min()),
                )
            )
            start += r
    return blocks


def scale(blocks: list[Block], s: torch.Tensor) -> list[Block]:
    """Each block times ``s (B, C, H, W)``, its window shrunk to where ``s`` is nonzero."""
    out = []
    for b in blocks:
        sw = s[(slice(None), slice(None), *b.window())]
        rows, cols = (sw != 0).any(0).any(0).nonzero(as_tuple=True)
        if len(rows) == 0:
            continue
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        coeff = b.coeff[..., r0:r1, c0:c1] * sw[:, None, :, r0:r1, c0:c1]
        out.append(Block(coeff, b.start, b.y + r0, b.x + c0))
    return out


def apply(op: ops.Op, blocks: list[Block], out_shape) -> list[Block]:
    """The blocks of ``op.linear(value)`` for a one-input local ``op``."""
    out = []
    for b in blocks:
        B, r = b.coeff.shape[:2]
        x = b.coeff.reshape(B * r, *b.coeff.shape[2:])
        if isinstance(op, ops.Conv):
            y, (oy, ox) = _conv(op.m, x, (b.y, b.x), out_shape[1:])
        elif isinstance(op, ops.ConvTranspose):
            y, (oy, ox) = _conv_transpose(op.m, x, (b.y, b.x), out_shape[1:])
        else:  # per-channel maps and channel slices keep the window
            y, (oy, ox) = op.linear(x), (b.y, b.x)
        if y is not None and y.numel() > 0:
            out.append(Block(y.reshape(B, r, *y.shape[1:]), b.start, oy, ox))
    return out


def combine(op: ops.Op, inputs: list[list[Block]], in_shapes) -> list[Block]:
    """The blocks of a sum or channel concatenation: a symbol's blocks from the inputs
    are merged on the union of their windows."""
    starts = sorted({b.start for blocks in inputs for b in blocks})
    by_start = [{b.start: b for b in blocks} for blocks in inputs]
    out = []
    for start in starts:
        present = [bs.get(start) for bs in by_start]
        found = [b for b in present if b is not None]
        some = found[0]
        y0, x0 = min(b.y for b in found), min(b.x for b in found)
        y1 = max(b.y + b.coeff.shape[-2] for b in found)
        x1 = max(b.x + b.coeff.shape[-1] for b in found)
        parts = []
        for b, shape in zip(present, in_shapes):
            if b is None:
                parts.append(
                    some.coeff.new_zeros(*some.coeff.shape[:2], shape[0], y1 - y0, x1 - x0)
                )
                continue
            h, w = b.coeff.shape[-2:]
            pad = (b.x - x0, x1 - b.x - w, b.y - y0, y1 - b.y - h)
            parts.append(F.pad(b.coeff, pad) if any(pad) else b.coeff)
        if isinstance(op, ops.Add):
            coeff = parts[0] + parts[1]
        else:
            coeff = torch.cat(parts, 2)
        out.append(Block(coeff, start, y0, x0))
    return out


def _pair(v):
    return (v, v) if isinstance(v, int) else tuple(v)


def _conv(m, x, corner, out_hw):
    """``conv2d`` (no bias) of a window ``x (N, C, h, w)`` at ``corner``: the outputs it
    reaches within ``out_hw`` and their corner."""
    k, s, p, d = (_pair(v) for v in (m.kernel_size, m.stride, m.padding, m.dilation))
    lo, pads = [], []
    for a in range(2):
        start, size = corner[a], x.shape[2 + a]
        o0 = max(0, -((d[a] * (k[a] - 1) - p[a] - start) // s[a]))  # ceil division
        o1 = min(out_hw[a], (start + size - 1 + p[a]) // s[a] + 1)
        if o1 <= o0:
            return None, (0, 0)
        need0 = o0 * s[a] - p[a]
        need1 = (o1 - 1) * s[a] - p[a] + d[a] * (k[a] - 1) + 1
        lo.append(o0)
        pads.append((start - need0, need1 - start - size))
    x = F.pad(x, (*pads[1], *pads[0]))
    return F.conv2d(x, m.weight, None, s, 0, d, m.groups), tuple(lo)


def _conv_transpose(m, x, corner, out_hw):
    """``conv_transpose2d`` (no bias) of a window at ``corner``, cropped to ``out_hw``."""
    k, s, p, d = (_pair(v) for v in (m.kernel_size, m.stride, m.padding, m.dilation))
    y = F.conv_transpose2d(x, m.weight, None, s, 0, 0, m.groups, d)
    lo, crop = [], []
    for a in range(2):
        o0 = corner[a] * s[a] - p[a]  # where the window's first output lands
        c0, c1 = max(0, -o0), min(y.shape[2 + a], out_hw[a] - o0)
        if c1 <= c0:
            return None, (0, 0)
        lo.append(o0 + c0)
        crop.append(slice(c0, c1))
    return y[:, :, crop[0], crop[1]], tuple(lo)
