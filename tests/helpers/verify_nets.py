"""Small random networks and input sets shared by the verifier tests."""

from __future__ import annotations

import torch
from torch import nn

from kpstudy.models.pooling import build_cell_pool


def _random_batch_norms(net: nn.Module, mean: float, bias: float) -> None:
    """Give every ``BatchNorm2d`` of ``net`` random running statistics (means in
    ``±mean``, variances in [0.5, 2]) and biases in ``±bias``, so that the folded affine
    maps are not the identity; then put ``net`` in eval mode."""
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.uniform_(-mean, mean)
                m.running_var.uniform_(0.5, 2.0)
                m.bias.uniform_(-bias, bias)
    net.eval()


class MixedNet(nn.Module):
    """Every supported operator once: conv, batch norm, ReLU, residual add, average pool
    (with padding, real pixels only), max pool, slicing, concatenation, transposed conv,
    flatten, linear. Input ``(B, 2, 8, 8)`` → ``(B, 6)``."""

    def __init__(self, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        self.conv1 = nn.Conv2d(2, 4, 3, padding=1)
        self.bn = nn.BatchNorm2d(4)
        self.conv2 = nn.Conv2d(4, 4, 3, padding=1)
        self.avg = nn.AvgPool2d(3, stride=1, padding=1, count_include_pad=False)
        self.max = nn.MaxPool2d(2)
        self.up = nn.ConvTranspose2d(6, 3, 2, stride=2)
        self.fc = nn.Linear(3 * 8 * 8, 6)
        with torch.no_grad():
            self.bn.running_mean.uniform_(-0.5, 0.5)
            self.bn.running_var.uniform_(0.5, 2.0)
            self.bn.weight.uniform_(0.5, 1.5)
            self.bn.bias.uniform_(-0.2, 0.2)
        self.eval()

    def forward(self, x):
        h = torch.relu(self.bn(self.conv1(x)))
        h = torch.relu(self.conv2(h) + h)
        a = self.avg(h)[:, :2, ::2, ::2]
        z = torch.cat([a, self.max(h)], 1)
        z = torch.relu(self.up(z))
        return self.fc(z.flatten(1))


class LocalNet(nn.Module):
    """The operators whose error symbols stay in spatial blocks, in awkward geometry:
    strided, padded, dilated and grouped convolutions, transposed convolutions with
    output padding, a batch norm on a sum, ReLUs in two parallel branches, channel
    slices and concatenation, on a non-square input ``(B, 2, 11, 9)`` → ``(B, 5)``."""

    def __init__(self, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        self.c1 = nn.Conv2d(2, 6, 3, stride=2, padding=2)
        self.c2 = nn.Conv2d(6, 6, 3, padding=2, dilation=2, groups=2)
        self.c3 = nn.Conv2d(6, 4, (1, 3), padding=(0, 1))
        self.bn = nn.BatchNorm2d(4)
        self.up = nn.ConvTranspose2d(6, 3, 3, stride=2, padding=1, output_padding=1)
        self.up2 = nn.ConvTranspose2d(3, 3, (2, 4), stride=(1, 2), padding=(0, 2))
        self.fc = nn.Linear(3 * 15 * 22, 5)
        with torch.no_grad():
            self.bn.running_mean.uniform_(-0.5, 0.5)
            self.bn.running_var.uniform_(0.5, 2.0)
        self.eval()

    def forward(self, x):
        h = torch.relu(self.c1(x))
        a = torch.relu(self.c2(h))
        b = torch.relu(self.c3(h))
        s = torch.relu(self.bn(a[:, 1:5] + b))
        z = torch.cat([s[:, :2], a[:, 4:], h[:, :2]], 1)
        z = torch.relu(self.up2(torch.relu(self.up(z))))
        return self.fc(z.flatten(1))


class PoolProxy(nn.Module):
    """A tiny keypoint proxy: conv backbone → two heatmap channels → per-channel cell
    pooling → flatten → concatenation. Input ``(B, 1, 10, 10)``."""

    def __init__(self, seed: int, centers=((3, 4), (6, 2)), dvs=((1, 1), (1, 2))):
        super().__init__()
        torch.manual_seed(seed)
        self.backbone = nn.Sequential(
            nn.Conv2d(1, 4, 3, padding=1), nn.ReLU(), nn.Conv2d(4, 2, 3, padding=1)
        )
        made = [build_cell_pool(c, d, (10, 10)) for c, d in zip(centers, dvs)]
        self.pools = nn.ModuleList([p for p, _ in made])
        self.targets = [t for _, t in made]
        self.group_sizes = [p.n_v * p.n_h for p in self.pools]
        self.eval()

    def forward(self, x):
        h = self.backbone(x)
        return torch.cat([p(h[:, k : k + 1]).flatten(1) for k, p in enumerate(self.pools)], 1)


class PatchNet(nn.Module):
    """A tiny heatmap network with a patch decoder: two convolutions (one strided) with
    ReLUs, then transposed convolutions whose kernels equal their strides with batch
    norms between them (an affine decoder). Input ``(B, 2, 8, 8)`` → ``(B, 3, 16, 16)``.
    ``bottleneck`` puts a one-channel layer in the decoder, which fusing would make
    costlier."""

    def __init__(self, seed: int, bottleneck: bool = False):
        super().__init__()
        torch.manual_seed(seed)
        mid = 1 if bottleneck else 4
        self.encoder = nn.Sequential(
            nn.Conv2d(2, 6, 3, stride=2, padding=1), nn.BatchNorm2d(6), nn.ReLU(),
            nn.Conv2d(6, 6, 3, padding=1), nn.ReLU(),
        )  # fmt: skip
        self.decoder = nn.Sequential(
            nn.ConvTranspose2d(6, 6, 2, stride=2, bias=False), nn.BatchNorm2d(6),
            nn.ConvTranspose2d(6, mid, 1, bias=False), nn.BatchNorm2d(mid),
            nn.ConvTranspose2d(mid, 3, 2, stride=2),
        )  # fmt: skip
        _random_batch_norms(self, mean=0.5, bias=0.3)

    def forward(self, x):
        return self.decoder(self.encoder(x))


class TinyResNet(nn.Module):
    """ResNet-18's shape in miniature: a stem with a strided max pooling, kpstudy's own
    ``BasicBlock`` with a strided 1×1 shortcut and one with the identity, then a decoder
    of 4×4 transposed convolutions of stride 2 with batch norms and ReLUs and a 1×1
    convolution to the heatmaps. Input ``(B, 3, 16, 16)`` → heatmaps ``(B, 3, 16, 16)``."""

    def __init__(self, seed: int):
        from kpstudy.models.resnet import BasicBlock

        super().__init__()
        torch.manual_seed(seed)
        self.net = nn.Sequential(
            nn.Conv2d(3, 8, 3, 1, 1, bias=False), nn.BatchNorm2d(8), nn.ReLU(),
            nn.MaxPool2d(3, 2, 1), BasicBlock(8, 12, 2), BasicBlock(12, 12, 1),
            nn.ConvTranspose2d(12, 8, 4, 2, 1, bias=False), nn.BatchNorm2d(8), nn.ReLU(),
            nn.ConvTranspose2d(8, 6, 4, 2, 1, bias=False), nn.BatchNorm2d(6), nn.ReLU(),
            nn.Conv2d(6, 3, 1),
        )  # fmt: skip
        _random_batch_norms(self, mean=0.3, bias=0.2)

    def forward(self, x):
        return self.net(x)


def block_hull_vertices(seed: int, n: int = 4, size: int = 16, block: int = 3) -> torch.Tensor:
    """A random seed image ``(3, size, size)`` in [0, 1] and ``n`` copies of it, each with
    one ``block × block`` square of one random colour at a random place (T-resnet's
    occlusions in miniature): ``(n + 1, 3, size, size)``."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(3, size, size, generator=g)
    images = [x0]
    for _ in range(n):
        r, c = torch.randint(0, size - block + 1, (2,), generator=g).tolist()
        x = x0.clone()
        x[:, r : r + block, c : c + block] = torch.rand(3, 1, 1, generator=g)
        images.append(x)
    return torch.stack(images)


def mlp(seed: int, sizes=(6, 5, 5, 3)) -> nn.Sequential:
    """A ReLU MLP on ``(B, sizes[0])``, float64."""
    torch.manual_seed(seed)
    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers[:-1]).double().eval()


def hull_vertices(seed: int, n: int, shape, spread: float = 0.3, dtype=torch.float32):
    """``n + 1`` images around a random seed image, shape ``(n+1, *shape)``."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(1, *shape, generator=g, dtype=dtype)
    return x0 + spread * torch.cat(
        [torch.zeros(1, *shape, dtype=dtype), torch.randn(n, *shape, generator=g, dtype=dtype)]
    )
