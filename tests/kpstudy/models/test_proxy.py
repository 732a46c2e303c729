"""kpstudy.models.proxy: the keypoint proxy's cells, its argmax against the heatmaps',
its spec and its refusals."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from kpstudy.models import build_proxy
from kpstudy.models.pooling import keypoint_pooling
from kpstudy.verify.graph import trace
from tests.helpers.heatmaps import gaussian_heatmaps

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
    assert _winner(proxy, gaussian_heatmaps(CENTERS, (64, 64))) == proxy.target_cells


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
                won = _winner(proxy, gaussian_heatmaps(moved, size, log=log))[k]
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
    assert _winner(proxy, gaussian_heatmaps([(40, 2)], (64, 64)))[0] == proxy.target_cells[0]
    assert _winner(proxy, gaussian_heatmaps([(40, 1)], (64, 64)))[0] != proxy.target_cells[0]

    proxy = build_proxy(
        nn.Identity(),
        keypoint_pooling([(0, 30)], [(3, 0)], (64, 64)),
        [(0, 30)],
        heatmap_size=(64, 64),
    )
    assert (
        _winner(proxy, gaussian_heatmaps([(4, 30)], (64, 64), log=True))[0] == proxy.target_cells[0]
    )
    assert _winner(proxy, gaussian_heatmaps([(4, 30)], (64, 64)))[0] != proxy.target_cells[0]


def test_proxy_spec_leaves_out_unverified_keypoints_and_traces():
    proxy = build_proxy(
        nn.Identity(),
        keypoint_pooling(CENTERS[:3], DV[:3], (64, 64)),
        CENTERS[:3],
        heatmap_size=(64, 64),
        verified=[True, False, True],
    )
    heat = gaussian_heatmaps(CENTERS[:3], (64, 64)).float()
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
