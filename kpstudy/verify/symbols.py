"""A zonotope's error symbols, each on the window of the activation it reaches.

A DeepZ error symbol (:mod:`kpstudy.verify.bounds`, method ``'zonotope'``) is made at one
unstable ReLU neuron, and each later convolution widens its reach by one kernel: through
most of a convolutional network a symbol touches a small window of each activation,
while a dense stack ``(B, E, C, H, W)`` pays for the whole activation per symbol. Here
the symbols made at one ReLU share a :class:`Block`: each symbol's coefficients on its
own ``(C, h, w)`` window of a ``(C, H, W)`` activation (zero outside it), the windows of
one size, their corners per symbol. A new symbol's window is its neuron (``1 × 1``); a
convolution maps the whole block in one call, each window to the outputs it reaches, so
a symbol costs its own reach and no more. Each operator says what it does with blocks
(:class:`kpstudy.verify.ops.Op`): convolutions, transposed convolutions, per-channel
maps and channel slices map blocks to blocks (:func:`apply`, each by its
``map_window``), sums and channel concatenations merge them (:func:`combine`); the
proxy's cell pool reads each block into the dense stack of its cells (:func:`cell_pool`),
so the full-resolution dense stack is never formed; any other operator gets the dense
stack (:func:`dense`). Within one value a symbol lives in one block only, so
``Σ_e |coefficient|`` (:func:`reach`) is exact.

Windows lie inside their activation: where a window would cross the border its corner
moves in and its data shifts with it (:func:`_inside`), which also drops what lies
outside, as a convolution's zero padding requires.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

if TYPE_CHECKING:
    from kpstudy.verify import ops


@dataclass
class Block:
    """Symbols ``[start, start + r)`` (rows of the dense stack) of a ``(C, H, W)`` value:
    symbol ``e`` of region ``b`` has coefficients ``coeff[b, e] (C, h, w)`` on rows
    ``y[b, e] … y[b, e] + h`` and columns ``x[b, e] … x[b, e] + w``, zero elsewhere
    (``y, x (B, r)`` int64; every window inside the value)."""

    coeff: torch.Tensor
    start: int
    y: torch.Tensor
    x: torch.Tensor

    @property
    def rows(self) -> int:
        return self.coeff.shape[1]

    def flat(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``coeff (B·r, C, h, w)`` and the corners ``y, x (B·r,)``."""
        B, r = self.coeff.shape[:2]
        return (
            self.coeff.reshape(B * r, *self.coeff.shape[2:]),
            self.y.reshape(-1),
            self.x.reshape(-1),
        )

    @classmethod
    def unflat(cls, coeff, start, y, x, B):
        return cls(coeff.reshape(B, -1, *coeff.shape[1:]), start, y.view(B, -1), x.view(B, -1))


def is_local(op: ops.Op, in_shapes, out_shape) -> bool:
    """Whether ``op`` maps blocks to blocks here: a local operator
    (:attr:`~kpstudy.verify.ops.Op.local`) between ``(C, H, W)`` values."""
    return op.local and len(out_shape) == 3 and all(len(s) == 3 for s in in_shapes)


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


def _shift(t: torch.Tensor, dy: torch.Tensor, dx: torch.Tensor, size) -> torch.Tensor:
    """``(N, C, h, w) → (N, C, *size)``: ``out[e, :, i, j] = t[e, :, i + dy[e], j + dx[e]]``,
    zero where that lies outside ``t``."""
    N, C, h, w = t.shape
    H, W = size
    if (H, W) == (h, w) and not (dy.any() or dx.any()):
        return t
    if N == 0:
        return t.new_zeros(N, C, H, W)
    if int(dy.min()) == int(dy.max()) and int(dx.min()) == int(dx.max()):  # one shift for all
        oy, ox = int(dy[0]), int(dx[0])
        return F.pad(t, (-ox, W - w + ox, -oy, H - h + oy))
    top, left = max(0, -int(dy.min())), max(0, -int(dx.min()))
    bottom, right = max(0, int(dy.max()) + H - h), max(0, int(dx.max()) + W - w)
    padded = F.pad(t, (left, right, top, bottom)) if top + bottom + left + right else t
    iy = (dy + top)[:, None] + torch.arange(H)  # (N, H)
    ix = (dx + left)[:, None] + torch.arange(W)  # (N, W)
    index = (iy[:, :, None] * (w + left + right) + ix[:, None, :]).view(N, 1, H * W)
    return padded.flatten(2).gather(2, index.expand(N, C, H * W)).view(N, C, H, W)


def _inside(t: torch.Tensor, y: torch.Tensor, x: torch.Tensor, size):
    """Windows ``t (N, C, h, w)`` at corners ``y, x (N,)`` (any, even outside) moved inside
    a ``size`` map: at most its size, corners clamped, data shifted (what lay outside
    dropped). Returns the windows and their corners."""
    H, W = size
    h, w = min(t.shape[2], H), min(t.shape[3], W)
    cy, cx = y.clamp(0, H - h), x.clamp(0, W - w)
    return _shift(t, cy - y, cx - x, (h, w)), cy, cx


def _window_index(y: torch.Tensor, x: torch.Tensor, h: int, w: int, W: int) -> torch.Tensor:
    """Flat indices ``(B, r, h·w)`` on a map of width ``W`` of the ``(h, w)`` windows at
    corners ``y, x (B, r)``."""
    iy = y[..., None] + torch.arange(h)  # (B, r, h)
    ix = x[..., None] + torch.arange(w)
    return (iy[..., :, None] * W + ix[..., None, :]).flatten(-2)


def _windows(s: torch.Tensor, y: torch.Tensor, x: torch.Tensor, h: int, w: int):
    """``s (B, C, H, W)`` read on the windows ``(h, w)`` at ``y, x (B, r)``: ``(B, r, C, h, w)``."""
    B, C, H, W = s.shape
    r = y.shape[1]
    index = _window_index(y, x, h, w, W).view(B, 1, r * h * w)
    out = s.flatten(2).gather(2, index.expand(B, C, r * h * w))
    return out.view(B, C, r, h, w).transpose(1, 2)


#: Window area up to which :func:`reach` adds one window offset at a time.
REACH_OFFSETS = 64


def reach(blocks: list[Block], like: torch.Tensor) -> torch.Tensor:
    """``Σ_e |coefficient of symbol e|`` per entry, ``(B, C, H, W)`` like ``like``, added
    up on a channel-last map (:meth:`~torch.Tensor.index_add_`): a small window one
    offset at a time (every symbol's ``C`` values there at once), a large one entry by
    entry in one call."""
    B, C, H, W = like.shape
    out = like.new_zeros(B * H * W, C)
    for b in blocks:
        r, h, w = b.rows, *b.coeff.shape[-2:]
        size = b.coeff.abs()
        if h * w <= REACH_OFFSETS:
            at = (torch.arange(B)[:, None] * (H * W) + b.y * W + b.x).reshape(-1)  # (B·r,)
            size = size.permute(3, 4, 0, 1, 2).contiguous()  # (h, w, B, r, C)
            for i in range(h):
                for j in range(w):
                    out.index_add_(0, at + (i * W + j), size[i, j].view(B * r, C))
        else:
            where = _window_index(b.y, b.x, h, w, W) + torch.arange(B)[:, None, None] * (H * W)
            index = where[:, :, None, :] * C + torch.arange(C)[:, None]  # (B, r, C, h·w)
            out.view(-1).index_add_(0, index.reshape(-1), size.reshape(-1))
    return out.view(B, H, W, C).permute(0, 3, 1, 2)


def gather(blocks: list[Block], rows: int, start: int, like: torch.Tensor, index: torch.Tensor):
    """The symbols' coefficients ``(B, rows, n)`` on the flat entries ``index (n,)`` of a
    value held as ``like (B, q, C, H, W)`` and ``blocks``, symbol ``e`` in row
    ``e − start`` (the dense stack's rows past its ``start`` affine ones, without forming
    it); ``rows`` is the number of symbols in all. Each window is read on the channels
    of ``index`` alone, through a map from entries to their place in ``index``."""
    B = like.shape[0]
    H, W = like.shape[-2:]
    entries, back = index.unique(return_inverse=True)
    n = len(entries)
    channels, channel_of = (entries // (H * W)).unique(return_inverse=True)
    lookup = torch.full((len(channels), H * W), n, dtype=torch.long)  # n: no entry
    lookup[channel_of, entries % (H * W)] = torch.arange(n)
    lookup = lookup.view(1, len(channels), H, W).expand(B, -1, -1, -1)
    out = like.new_zeros(B, rows, n + 1)
    for b in blocks:
        h, w = b.coeff.shape[-2:]
        at = _windows(lookup, b.y, b.x, h, w).reshape(B, b.rows, -1)
        values = b.coeff[:, :, channels].reshape(B, b.rows, -1)
        r0 = b.start - start
        out[:, r0 : r0 + b.rows] = out[:, r0 : r0 + b.rows].scatter(2, at, values)
    return out[..., back]


#: Window entries :func:`overlap` reads at a time (its float64 temporaries stay ~100 MB).
OVERLAP_ELEMENTS = 2**22


def overlap(blocks: list[Block], channel: int, y: torch.Tensor, x: torch.Tensor, size):
    """``Σ_e |s_e(i)| + |s_e(c)| − |s_e(i) − s_e(c)|`` over the symbols ``e`` of region
    ``b`` whose window covers the entry ``c = (channel, y[b], x[b])``, for every entry
    ``i`` of that channel: ``(B, H·W)`` for ``y, x (B,)`` and a ``(C, H, W)`` value of
    ``size = (H, W)``.

    With the reach ``ρ`` (:func:`reach`), ``Σ_e |s_e(i) − s_e(c)| = ρ(i) + ρ(c) −
    overlap(i)`` exactly (a symbol whose window misses ``c`` adds ``|s_e(i)|``), so a
    margin's share of the symbols costs the few symbols that reach ``c`` rather than a
    read of every symbol on every entry. ``blocks`` must not be empty. Computed and
    returned in float64: the difference cancels, so its error stays that of the reach."""
    H, W = size
    B = y.shape[0]
    out = torch.zeros(B * H * W, dtype=torch.float64)
    for b in blocks:
        h, w = b.coeff.shape[-2:]
        dy, dx = y[:, None] - b.y, x[:, None] - b.x  # (B, r): c within each window
        region, row = ((dy >= 0) & (dy < h) & (dx >= 0) & (dx < w)).nonzero(as_tuple=True)
        step = max(1, OVERLAP_ELEMENTS // (h * w))  # windows at a time: bounded memory
        for first in range(0, len(region), step):
            reg, e = region[first : first + step], row[first : first + step]
            window = b.coeff[reg, e, channel].double()  # (n, h, w)
            at_c = window[torch.arange(len(reg)), dy[reg, e], dx[reg, e]][:, None, None]
            term = window.abs() + at_c.abs() - (window - at_c).abs()
            iy = b.y[reg, e][:, None, None] + torch.arange(h)[:, None]  # (n, h, 1)
            ix = b.x[reg, e][:, None, None] + torch.arange(w)  # (n, 1, w)
            index = reg[:, None, None] * (H * W) + iy * W + ix
            out.index_add_(0, index.reshape(-1), term.reshape(-1))
    return out.view(B, H * W)


def dense(mid: torch.Tensor, blocks: list[Block], rows: int) -> torch.Tensor:
    """The dense stack ``(B, rows, *S)``: ``mid (B, q, *S)`` then every symbol's row, each
    block's windows (``S = (C, H, W)``) scattered into its rows."""
    B, q = mid.shape[:2]
    out = mid.new_zeros(B, rows, *mid.shape[2:])
    out[:, :q] = mid
    if not blocks:
        return out
    C, H, W = mid.shape[2:]
    flat = out.view(B, rows, C, H * W)
    for b in blocks:
        r, h, w = b.rows, *b.coeff.shape[-2:]
        index = _window_index(b.y, b.x, h, w, W)[:, :, None].expand(B, r, C, h * w)
        flat[:, b.start : b.start + r].scatter_(3, index, b.coeff.reshape(B, r, C, h * w))
    return out


def cell_pool(op: ops.CellPool, mid: torch.Tensor, blocks: list[Block], rows: int):
    """The dense stack ``(B, rows, 1, n_v, n_h)`` of the cell pool ``op`` of a value held
    as ``θ`` rows ``mid (B, q, 1, H, W)`` and symbol ``blocks``.

    A cell is a ``k_v × k_h`` window of the padded map, so each symbol's window is
    widened to whole cells (a few pixels) and pooled on its own; the
    ``(B, rows, 1, H, W)`` stack that :func:`dense` would build and pad is never formed."""
    B, q = mid.shape[:2]
    pooled_mid = op.forward(mid.reshape(B * q, *mid.shape[2:])).reshape(B, q, 1, op.n_v, op.n_h)
    (kv, kh), (left, _, top, _) = op.kernel_size, op.pad
    pooled = []
    for b in blocks:
        coeff, y, x = b.flat()
        h, w = coeff.shape[-2:]
        y, x = y + top, x + left  # the windows in the padded map
        c0, d0 = y // kv, x // kh  # their first cells
        nv = int(((y + h + kv - 1) // kv - c0).max())
        nh = int(((x + w + kh - 1) // kh - d0).max())
        cells = _shift(coeff, c0 * kv - y, d0 * kh - x, (nv * kv, nh * kh))
        if (kv, kh) != (1, 1):
            cells = F.avg_pool2d(cells, (kv, kh))
        cells, c0, d0 = _inside(cells, c0, d0, (op.n_v, op.n_h))
        pooled.append(Block.unflat(cells, b.start, c0, d0, B))
    out = dense(pooled_mid, pooled, rows)
    out[:, q:] *= op.scale.to(mid.dtype)  # the θ rows have it from op.forward
    return out


def make(mu: torch.Tensor, start: int) -> list[Block]:
    """New symbols for the nonzero entries of ``mu (B, C, H, W)`` (one each, coefficient
    ``μ`` on its own neuron), numbered from ``start`` in the order of the flat entries:
    one block whose rows are the batch's largest count (shorter regions get zero rows)."""
    B, C, H, W = mu.shape
    flat = mu.reshape(B, -1)
    region, entry = (flat > 0).nonzero(as_tuple=True)  # by region, then entry
    if len(entry) == 0:
        return []
    count = torch.bincount(region, minlength=B)
    row = torch.arange(len(entry)) - (count.cumsum(0) - count)[region]
    r = int(count.max())
    order = torch.zeros(B, r, dtype=torch.long)
    order[region, row] = entry
    coeff = flat.new_zeros(B, r, C)
    coeff = coeff.index_put((region, row, entry // (H * W)), flat[region, entry])
    return [Block(coeff.view(B, r, C, 1, 1), start, order // W % H, order % W)]


def scale(blocks: list[Block], s: torch.Tensor) -> list[Block]:
    """Each block times ``s (B, C, H, W)``; a block's windows shrink to the largest extent
    where a symbol stays nonzero, a block that is zero everywhere goes."""
    out = []
    H, W = s.shape[-2:]
    for b in blocks:
        B, r, C, h, w = b.coeff.shape
        coeff = b.coeff * _windows(s, b.y, b.x, h, w)
        live = (coeff != 0).any(2)  # (B, r, h, w)
        rows_live, cols_live = live.any(-1), live.any(-2)  # (B, r, h), (B, r, w)
        if not rows_live.any():
            continue
        first_y, last_y = _extent(rows_live)
        first_x, last_x = _extent(cols_live)
        hh, ww = int((last_y - first_y).max()) + 1, int((last_x - first_x).max()) + 1
        y, x = b.y + first_y, b.x + first_x
        if (hh, ww) != (h, w):
            y, x = y.clamp(max=H - hh), x.clamp(max=W - ww)
            flat = _shift(
                coeff.reshape(B * r, C, h, w),
                (y - b.y).reshape(-1),
                (x - b.x).reshape(-1),
                (hh, ww),
            )
            coeff = flat.view(B, r, C, hh, ww)
        else:
            y, x = b.y, b.x
        out.append(Block(coeff, b.start, y, x))
    return out


def _extent(live: torch.Tensor):
    """First and last true index along the last axis of ``live (…, n)`` (0, 0 where none)."""
    n = live.shape[-1]
    index = torch.arange(n)
    first = torch.where(live, index, n).amin(-1)
    last = torch.where(live, index, -1).amax(-1)
    none = last < 0
    return first.masked_fill(none, 0), last.masked_fill(none, 0)


def apply(op: ops.Op, blocks: list[Block], out_shape) -> list[Block]:
    """The blocks of ``op.linear(value)`` for a one-input local ``op``, each block's
    windows mapped by the operator (:meth:`~kpstudy.verify.ops.Op.map_window`)."""
    out = []
    for b in blocks:
        B = b.coeff.shape[0]
        x, y0, x0 = b.flat()
        y, oy, ox = op.map_window(x, y0, x0, out_shape[1:])
        if y.numel() > 0:
            out.append(Block.unflat(y, b.start, oy, ox, B))
    return out


def combine(op: ops.Op, inputs: list[list[Block]], in_shapes) -> list[Block]:
    """The blocks of a local operator of several inputs (a sum, a channel
    concatenation): a symbol's windows from the inputs are placed on their union, where
    ``op.linear`` maps them."""
    starts = sorted({b.start for blocks in inputs for b in blocks})
    by_start = [{b.start: b for b in blocks} for blocks in inputs]
    H, W = in_shapes[0][1:]
    out = []
    for start in starts:
        present = [bs.get(start) for bs in by_start]
        found = [b for b in present if b is not None]
        some = found[0]
        B, r = some.coeff.shape[:2]
        y0 = torch.stack([b.y for b in found]).amin(0)
        x0 = torch.stack([b.x for b in found]).amin(0)
        y1 = torch.stack([b.y + b.coeff.shape[-2] for b in found]).amax(0)
        x1 = torch.stack([b.x + b.coeff.shape[-1] for b in found]).amax(0)
        hh, ww = int((y1 - y0).max()), int((x1 - x0).max())
        y0, x0 = y0.clamp(max=H - hh), x0.clamp(max=W - ww)
        parts = []
        for b, shape in zip(present, in_shapes):
            if b is None:
                parts.append(some.coeff.new_zeros(B * r, shape[0], hh, ww))
                continue
            coeff, y, x = b.flat()
            parts.append(_shift(coeff, y0.reshape(-1) - y, x0.reshape(-1) - x, (hh, ww)))
        coeff = op.linear(*parts)
        out.append(Block.unflat(coeff, start, y0.reshape(-1), x0.reshape(-1), B))
    return out


def _pair(v):
    return (v, v) if isinstance(v, int) else tuple(v)


def reached_outputs(k, s, p, d, size, y, x0):
    """The outputs a sliding window (kernel ``k``, stride ``s``, padding ``p``, dilation
    ``d``, ``(h, w)`` pairs) reaches from windows of ``size (h, w)`` at corners ``y, x0
    (N,)``: per axis the first output reached ``(N,)``, the input entries between its
    input window's start and the window's ``(N,)`` (≥ 0), the outputs to compute (the
    most any window reaches, at least 1) and the input length they read."""
    first, lead, count, length = [], [], [], []
    for a, start in enumerate((y, x0)):
        span = d[a] * (k[a] - 1)
        o0 = -((span - p[a] - start) // s[a])  # the first output reached (ceil division)
        o1 = (start + size[a] - 1 + p[a]) // s[a]  # the last
        ahead = start - (o0 * s[a] - p[a])
        n = max(1, int((o1 - o0).max()) + 1)  # 0 where no window reaches an output
        first.append(o0)
        lead.append(ahead)
        count.append(n)
        length.append(max((n - 1) * s[a] + span + 1, int((ahead + size[a]).max())))
    return first, lead, count, length


def conv_windows(m, x, y, x0, out_hw):
    """``conv2d`` (no bias) of windows ``x (N, C, h, w)`` at corners ``y, x0 (N,)``: each
    window's outputs (those it reaches, placed inside ``out_hw``) and their corners."""
    k, s, p, d = (_pair(v) for v in (m.kernel_size, m.stride, m.padding, m.dilation))
    first, lead, _, length = reached_outputs(k, s, p, d, x.shape[2:], y, x0)
    if s == (1, 1):  # every window needs its kernel's span on each side
        out = F.conv2d(x, m.weight, None, s, (d[0] * (k[0] - 1), d[1] * (k[1] - 1)), d, m.groups)
    else:
        x = _shift(x, -lead[0], -lead[1], length)
        out = F.conv2d(x, m.weight, None, s, 0, d, m.groups)
    return _inside(out, first[0], first[1], out_hw)


def pool_windows(op: ops.MaxPool, x, y, x0, out_hw):
    """Max pooling (``op``'s kernel, stride and padding) of windows ``x (N, C, h, w)`` at
    corners ``y, x0 (N,)``, zero outside them: each window's outputs (those it reaches,
    placed inside ``out_hw``) and their corners. On non-negative windows, the extent of
    the outputs a window's entries can be chosen by."""
    first, lead, _, length = reached_outputs(
        op.kernel, op.stride, op.padding, (1, 1), x.shape[2:], y, x0
    )
    out = F.max_pool2d(_shift(x, -lead[0], -lead[1], length), op.kernel, op.stride)
    return _inside(out, first[0], first[1], out_hw)


def pool_chosen(op: ops.MaxPool, blocks: list[Block], row, col, out_shape) -> list[Block]:
    """The blocks of a max pooling's output where each output entry equals one input
    entry, ``row, col (B, C, H_out, W_out)`` (int64; row −1 for an entry that copies
    none, whose symbols' coefficients are then 0): a symbol's coefficient at an
    output is its coefficient at the chosen input, zero where that lies outside its
    window."""
    out = []
    Ho, Wo = out_shape[1:]
    for b in blocks:
        B, r, C, h, w = b.coeff.shape
        first, _, (nh, nw), _ = reached_outputs(
            op.kernel, op.stride, op.padding, (1, 1), (h, w), b.y.reshape(-1), b.x.reshape(-1)
        )
        nh, nw = min(nh, Ho), min(nw, Wo)
        oy = first[0].view(B, r).clamp(0, Ho - nh)
        ox = first[1].view(B, r).clamp(0, Wo - nw)
        ly = _windows(row, oy, ox, nh, nw) - b.y[..., None, None, None]  # (B, r, C, nh, nw)
        lx = _windows(col, oy, ox, nh, nw) - b.x[..., None, None, None]
        inside = (ly >= 0) & (ly < h) & (lx >= 0) & (lx < w)
        at = torch.where(inside, ly * w + lx, 0).flatten(-2)
        coeff = b.coeff.flatten(-2).gather(-1, at).view(B, r, C, nh, nw)
        out.append(Block(coeff * inside, b.start, oy, ox))
    return out


def conv_transpose_windows(m, x, y, x0, out_hw):
    """``conv_transpose2d`` (no bias) of windows at corners ``y, x0``, placed inside ``out_hw``."""
    k, s, p, d = (_pair(v) for v in (m.kernel_size, m.stride, m.padding, m.dilation))
    out = F.conv_transpose2d(x, m.weight, None, s, 0, 0, m.groups, d)
    return _inside(out, y * s[0] - p[0], x0 * s[1] - p[1], out_hw)
