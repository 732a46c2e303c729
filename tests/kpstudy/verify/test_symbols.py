"""kpstudy.verify.symbols: a zonotope's error symbols held in blocks of windows, against
the dense stack ``(B, rows, C, H, W)`` that each function must equal: new symbols, the
windows an operator maps, sums and concatenations, scaling, reach, reading entries and
the cell pool."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.verify import ops, symbols

Q = 3  # θ rows before the symbols
B, C, H, W = 2, 2, 9, 8


def positive_entries(seed, shape=(B, C, H, W), share=0.2):
    """Nonnegative ``μ`` with about ``share`` of its entries positive, the corners included,
    and region 1 holding fewer than region 0 (its block then has zero rows)."""
    g = torch.Generator().manual_seed(seed)
    mu = torch.rand(*shape, generator=g, dtype=torch.float64)
    mu = mu * (torch.rand(*shape, generator=g, dtype=torch.float64) < share)
    mu[:, :, 0, 0] = mu[:, :, -1, -1] = 0.5
    mu[1, :, : shape[2] // 2] = 0.0
    return mu


def dense_symbols(blocks, rows, shape):
    """The symbol rows of the dense stack of ``blocks`` on a value of shape ``shape``."""
    mid = torch.zeros(shape[0], Q, *shape[1:], dtype=torch.float64)
    return symbols.dense(mid, blocks, Q + rows)[:, Q:]


def rows_of(blocks):
    return max((b.start - Q + b.rows for b in blocks), default=0)


def conv_blocks(seed):
    """Symbols of a ReLU mapped by a 3×3 convolution: windows larger than one entry, some
    against the border."""
    mu = positive_entries(seed)
    conv = ops.Conv(nn.Conv2d(C, C, 3, padding=1).double())
    return symbols.apply(conv, symbols.make(mu, Q), (C, H, W)), rows_of(symbols.make(mu, Q))


def test_new_symbols_are_one_per_positive_entry_in_flat_order():
    mu = positive_entries(0)
    blocks = symbols.make(mu, Q)
    (block,) = blocks
    count = (mu.flatten(1) > 0).sum(1)
    assert block.start == Q and block.rows == int(count.max()) and block.coeff.shape[-2:] == (1, 1)
    D = dense_symbols(blocks, block.rows, mu.shape).flatten(2)  # (B, rows, C·H·W)
    assert ((D != 0).sum(2) <= 1).all()  # a symbol on its own neuron
    torch.testing.assert_close(D.sum(1), mu.flatten(1), rtol=0, atol=0)
    for b in range(B):
        where = D[b, : count[b]].abs().argmax(1)
        assert (where.diff() > 0).all()  # numbered in the order of the flat entries
        assert not D[b, count[b] :].any()  # the shorter region's rows are zero
    mid = torch.randn(B, Q, C, H, W, dtype=torch.float64)
    torch.testing.assert_close(symbols.dense(mid, blocks, Q + block.rows)[:, :Q], mid)
    assert symbols.make(torch.zeros(B, C, H, W), Q) == []


@pytest.mark.parametrize(
    "layer",
    [
        nn.Conv2d(C, 3, 3, padding=1),
        nn.Conv2d(C, 3, 3, stride=2, padding=1),
        nn.Conv2d(C, 4, 5, padding=2, groups=2),
        nn.Conv2d(C, 3, 3, padding=2, dilation=2),
        nn.Conv2d(C, 3, 2, stride=2),
        nn.ConvTranspose2d(C, 3, 4, stride=2, padding=1),
        nn.ConvTranspose2d(C, 3, 2, stride=2),
    ],
    ids=str,
)
def test_an_operator_maps_each_window_as_it_maps_the_dense_stack(layer):
    """Each window goes to the outputs it reaches (its corner moved inside the output where
    it would cross the border), and the blocks read as the operator's linear map of the
    dense stack."""
    blocks, rows = conv_blocks(1)
    op = (ops.Conv if isinstance(layer, nn.Conv2d) else ops.ConvTranspose)(layer.double())
    before = dense_symbols(blocks, rows, (B, C, H, W))
    after = op.linear(before.flatten(0, 1))
    out_shape = tuple(after.shape[1:])
    mapped = symbols.apply(op, blocks, out_shape)
    for b in mapped:
        h, w = b.coeff.shape[-2:]
        assert (b.y >= 0).all() and (b.y + h <= out_shape[1]).all()
        assert (b.x >= 0).all() and (b.x + w <= out_shape[2]).all()
    got = dense_symbols(mapped, rows, (B, *out_shape))
    torch.testing.assert_close(got, after.view(B, rows, *out_shape), rtol=1e-12, atol=1e-12)


def test_windows_that_a_strided_convolution_skips_map_to_zero():
    """A 1×1 window on an odd row and column reaches no output of a 1×1 convolution of
    stride 2 (a residual block's shortcut): alone in its block or beside a window that
    does reach one."""
    layer = nn.Conv2d(C, 3, 1, stride=2).double()
    op = ops.Conv(layer)
    for entries in ([(3, 5)], [(3, 5), (2, 4)]):
        mu = torch.zeros(1, C, H, W, dtype=torch.float64)
        for y, x in entries:
            mu[0, :, y, x] = 1.0
        blocks = symbols.make(mu, Q)
        rows = rows_of(blocks)
        before = dense_symbols(blocks, rows, (1, C, H, W))
        after = op.linear(before.flatten(0, 1))
        mapped = symbols.apply(op, blocks, tuple(after.shape[1:]))
        got = dense_symbols(mapped, rows, (1, *after.shape[1:]))
        torch.testing.assert_close(got, after.view(1, rows, *after.shape[1:]), rtol=0, atol=0)


@pytest.mark.parametrize("seed", range(3))
def test_a_max_pooling_copies_each_chosen_inputs_symbols_and_drops_the_undecided(seed):
    """Each output of a 3×3 stride-2 max pooling takes the symbols of the input it
    chose (any entry of its window: ``pool_chosen``), none where no input was chosen (an
    undecided window), on windows larger than one entry; and ``pool_windows`` reaches
    every output a window's entry can be chosen by."""
    pool = ops.MaxPool(nn.MaxPool2d(3, 2, 1))
    blocks, rows = conv_blocks(seed)
    Ho, Wo = (H + 1) // 2, (W + 1) // 2
    g = torch.Generator().manual_seed(seed)
    oy, ox = torch.arange(Ho)[:, None] * 2 - 1, torch.arange(Wo) * 2 - 1
    row = (oy + torch.randint(0, 3, (B, C, Ho, Wo), generator=g)).clamp(0, H - 1)
    col = (ox + torch.randint(0, 3, (B, C, Ho, Wo), generator=g)).clamp(0, W - 1)
    row[torch.rand(B, C, Ho, Wo, generator=g) < 0.3] = -1  # undecided
    before = dense_symbols(blocks, rows, (B, C, H, W)).flatten(3)  # (B, rows, C, H·W)
    index = (row.clamp_min(0) * W + col).flatten(2)[:, None].expand(-1, rows, -1, -1)
    want = (before.gather(3, index) * (row >= 0).flatten(2)[:, None]).view(B, rows, C, Ho, Wo)
    got = dense_symbols(
        symbols.pool_chosen(pool, blocks, row, col, (C, Ho, Wo)), rows, (B, C, Ho, Wo)
    )
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    reached = dense_symbols(
        symbols.apply(
            pool, [symbols.Block(b.coeff.abs() + 1, b.start, b.y, b.x) for b in blocks], (C, Ho, Wo)
        ),
        rows,
        (B, C, Ho, Wo),
    )
    assert ((reached > 0) | (want == 0)).all()


def test_a_sum_and_a_channel_concatenation_merge_the_blocks_of_their_inputs():
    mu = positive_entries(2)
    first = symbols.make(mu, Q)
    r = first[0].rows
    conv = ops.Conv(nn.Conv2d(C, C, 3, padding=1).double())
    wide = ops.Conv(nn.Conv2d(C, C, 5, padding=2).double())
    left = symbols.apply(conv, first, (C, H, W))
    # The right branch: the same symbols through another map, and new ones of its own.
    right = symbols.apply(wide, first, (C, H, W)) + symbols.make(positive_entries(3), Q + r)
    rows = rows_of(right)
    shape = (C, H, W)
    dense_left, dense_right = (dense_symbols(x, rows, (B, *shape)) for x in (left, right))
    added = symbols.combine(ops.Add(), [left, right], [shape, shape])
    torch.testing.assert_close(dense_symbols(added, rows, (B, *shape)), dense_left + dense_right)
    stacked = symbols.combine(ops.Cat(2, 1), [left, right], [shape, shape])
    want = torch.cat([dense_left, dense_right], 2)
    torch.testing.assert_close(dense_symbols(stacked, rows, (B, 2 * C, H, W)), want)


def test_scaling_multiplies_shrinks_the_windows_and_drops_dead_blocks():
    blocks, rows = conv_blocks(4)
    s = torch.zeros(B, C, H, W, dtype=torch.float64)
    s[:, :, 2:5, 3:5] = torch.rand(B, C, 3, 2, dtype=torch.float64) + 0.5
    scaled = symbols.scale(blocks, s)
    want = dense_symbols(blocks, rows, (B, C, H, W)) * s[:, None]
    torch.testing.assert_close(dense_symbols(scaled, rows, (B, C, H, W)), want)
    assert all(b.coeff.shape[-2] <= 3 and b.coeff.shape[-1] <= 2 for b in scaled)  # live extent
    assert symbols.scale(blocks, torch.zeros_like(s)) == []


@pytest.mark.parametrize("offsets", [64, 0])
def test_reach_is_the_dense_stacks_l1_norm_whichever_way_it_adds(offsets, monkeypatch):
    monkeypatch.setattr(symbols, "REACH_OFFSETS", offsets)
    blocks, rows = conv_blocks(5)
    blocks += symbols.make(positive_entries(6), Q + rows)
    dense = dense_symbols(blocks, rows_of(blocks), (B, C, H, W))
    like = torch.zeros(B, C, H, W, dtype=torch.float64)
    torch.testing.assert_close(symbols.reach(blocks, like), dense.abs().sum(1))


def test_gather_reads_the_dense_rows_at_chosen_entries():
    blocks, rows = conv_blocks(7)
    dense = dense_symbols(blocks, rows, (B, C, H, W)).flatten(2)
    index = torch.tensor([0, H * W - 1, H * W, 5, 5, C * H * W - 1, 17])  # repeated, 2 channels
    like = torch.zeros(B, Q, C, H, W, dtype=torch.float64)
    got = symbols.gather(blocks, rows, Q, like, index)
    torch.testing.assert_close(got, dense[..., index], rtol=0, atol=0)


@pytest.mark.parametrize("seed", range(3))
def test_a_margins_symbol_share_is_reach_plus_reach_less_the_overlap(seed):
    """``Σ_e |s_e(i) − s_e(c)| = ρ(i) + ρ(c) − overlap(i)`` on every entry ``i`` of a
    channel, for a candidate ``c`` inside some windows, on a border, or reached by none."""
    blocks, rows = conv_blocks(seed)
    D = dense_symbols(blocks, rows, (B, C, H, W))  # (B, E, C, H, W)
    rho = symbols.reach(blocks, torch.zeros(B, C, H, W, dtype=torch.float64)).flatten(2)
    g = torch.Generator().manual_seed(seed)
    for channel in range(C):
        s = D[:, :, channel].flatten(2)  # (B, E, H·W)
        for _ in range(4):
            y = torch.randint(0, H, (B,), generator=g)
            x = torch.randint(0, W, (B,), generator=g)
            c = y * W + x
            at_c = s.gather(2, c.view(B, 1, 1).expand(-1, s.shape[1], 1))
            expected = (s - at_c).abs().sum(1)  # (B, H·W)
            shared = symbols.overlap(blocks, channel, y, x, (H, W))
            got = rho[:, channel] + rho[:, channel].gather(1, c[:, None]) - shared
            torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


def test_the_cell_pool_reads_blocks_as_it_pools_the_dense_stack():
    """Each window widened to whole cells of the padded map and pooled on its own gives
    the cell pool of the dense stack, ``θ`` rows included."""
    mu = positive_entries(8, shape=(B, 1, H, W), share=0.3)
    conv = ops.Conv(nn.Conv2d(1, 1, 3, padding=1).double())
    blocks = symbols.apply(conv, symbols.make(mu, Q), (1, H, W))
    rows = Q + rows_of(blocks)
    # (H + 0 + 3, W + 1 + 1) = (12, 10): 4 × 5 cells of 3 × 2 pixels.
    scale = torch.rand(4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(8))
    pool = ops.CellPool((1, 1, 0, 3), (3, 2), scale + 0.5)
    mid = torch.randn(B, Q, 1, H, W, dtype=torch.float64)
    dense = symbols.dense(mid, blocks, rows)
    want = pool.forward(dense.flatten(0, 1)).view(B, rows, 1, 4, 5)
    torch.testing.assert_close(symbols.cell_pool(pool, mid, blocks, rows), want)


@pytest.mark.parametrize("shape", [(2, 40, 7), (1, 33, 65, 64), (3, 20, 8, 8, 65)])
def test_l1_rows_sums_absolute_rows_whichever_way_it_goes(shape):
    """Short rows take one reduction, long ones go a few at a time: the same sums, and
    the same gradient."""
    from kpstudy.verify.symbols import L1_DIRECT, l1_rows

    x = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    assert (x[:1, :1].numel() <= L1_DIRECT) == (shape[2:] == (7,))
    out = l1_rows(x)
    torch.testing.assert_close(out, x.abs().sum(1), rtol=1e-12, atol=1e-12)
    out.sum().backward()
    torch.testing.assert_close(x.grad, x.detach().sign())
