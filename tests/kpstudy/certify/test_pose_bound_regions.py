"""kpstudy.certify.pose_bound_regions: the region search's pooling."""

import numpy as np
import torch

from kpstudy.certify.pose_bound_regions import region_pooling


def test_at_stride_1_the_proxy_is_the_backbones_own_output():
    """The stride-1 search bounds the backbone itself (its error symbols stay in blocks):
    sound only because the proxy's one-pixel cells are the heatmaps in the backbone's
    own order, checked here with keypoints on the map's edges."""
    from kpstudy.models.cnn import HeatmapCNNPatchDecoder
    from kpstudy.models.proxy import build_proxy

    torch.manual_seed(0)
    net = HeatmapCNNPatchDecoder(5).eval()
    centers = np.array([[0, 0], [63, 0], [0, 63], [63, 63], [20, 41]])
    proxy = build_proxy(net, region_pooling(centers, 1, 64), centers).eval()
    assert proxy.spec.group_sizes == [64 * 64] * 5
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(proxy(x), net(x).flatten(1), rtol=0, atol=0)
