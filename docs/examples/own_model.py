"""Your own heatmap network and a hull of your own images, start to verdict.

Run from the repository root: ``.venv/bin/python docs/examples/own_model.py`` (seconds
on one core). Replace :class:`TinyHeatmapNet` by your trained network, the scene by your
camera and object, and :func:`hull_images` by your images; the rest stays.
"""

import numpy as np
import torch
from torch import nn

from kpstudy.certify import SeedImage, certify
from kpstudy.models.preprocess import scale_factors, to_input_pixels, to_model_input
from kpstudy.pose.geometry import project
from kpstudy.verify import ArgmaxSpec, ConvexHull, verify

# The scene: the object's keypoints (metres, object frame), a pinhole camera for
# 320×320 images, and the seed image's pose (object → camera, x_c = R p + t).
POINTS_3D = np.array(
    [[-20, 0, 0], [20, 0, 0], [0, -15, 0], [0, 15, 0], [0, 0, 3], [5, 5, -2]], float
)
IMAGE_SIZE = (320, 320)  # (W, H)
CAMERA = np.array([[300.0, 0, 159.5], [0, 300.0, 159.5], [0, 0, 1]])
R, T = np.eye(3), np.array([0.0, 0.0, 70.0])
KEYPOINTS = project(POINTS_3D, R, T, CAMERA)  # (u, v) in image pixels


class TinyHeatmapNet(nn.Module):
    """Images ``(B, 3, 32, 32)`` in [0, 1] → one 32×32 heatmap per keypoint, built of
    layers the verifier supports (``Conv2d``, ``ConvTranspose2d``, ``ReLU``, …)."""

    input_size = 32  # what certify resizes your images to
    heatmap_size = 32

    def __init__(self, keypoints: int) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(3, 8, 4, stride=4),  # → (8, 8, 8)
            nn.ReLU(),
            nn.Conv2d(8, 4, 8),  # → (4, 1, 1): the whole image
            nn.ReLU(),
            nn.ConvTranspose2d(4, keypoints, 32),  # → (keypoints, 32, 32)
        )

    def forward(self, x):
        return self.layers(x)


def make_model() -> TinyHeatmapNet:
    """A stand-in for a trained network: random weights, and heatmaps nudged to peak at
    the seed's keypoints (training would put them there)."""
    torch.manual_seed(0)
    model = TinyHeatmapNet(len(POINTS_3D))
    peaks = np.rint(to_input_pixels(KEYPOINTS, scale_factors(IMAGE_SIZE, 32))).astype(int)
    with torch.no_grad():
        model.layers[2].bias.fill_(1.0)
        for k, (u, v) in enumerate(peaks):
            model.layers[4].weight[:, k, v, u] += 5.0
    return model.eval()


def hull_images() -> np.ndarray:
    """The seed image first, then its perturbed copies: ``(n+1, H, W, 3)`` in [0, 255]."""
    seed = np.random.default_rng(0).uniform(0, 255, (*IMAGE_SIZE[::-1], 3))
    brighter, darker, more_contrast = seed + 20, seed - 20, 128 + 1.2 * (seed - 128)
    return np.clip(np.stack([seed, brighter, darker, more_contrast]), 0, 255)


def main() -> None:
    model, images = make_model(), hull_images()

    # 1. The verifier alone: does each keypoint's argmax pixel stay the seed's over
    #    every image of the hull?
    x = to_model_input(images, size=model.input_size)  # (n+1, 3, 32, 32) in [0, 1]
    with torch.no_grad():
        heatmaps = model(x[:1])[0]  # (K, 32, 32)
    targets = heatmaps.flatten(1).argmax(1).tolist()  # each keypoint's argmax on the seed
    spec = ArgmaxSpec([heatmaps[0].numel()] * len(heatmaps), targets)
    result = verify(model, ConvexHull(x), spec, max_nodes=16)
    print(f"verify: {result.status} ({result.nodes} nodes)")

    # 2. The pose: does its error stay within ε = α·[10°, 10°, 10°, 4 m, 4 m, 20 m] over
    #    the hull? The paper's allocation method (κ: its sensitivity margin) and the
    #    pose-bound method, each under a node budget (the same verdicts on any machine).
    seed = SeedImage(0, KEYPOINTS, CAMERA, POINTS_3D, IMAGE_SIZE)
    budgets = dict(max_nodes=16, pose_bound_method="zonotope", pose_bound_nodes=8)
    record = certify(model, images, seed, alpha=1.0, kappa=1.0, pose_bound_timeout=60, **budgets)
    # record: one dict (kpstudy.certify.certify_cells lists its keys)
    print(f"certify: allocation method {record['status']}, pose-bound method {record['pb_status']}")


if __name__ == "__main__":
    main()
