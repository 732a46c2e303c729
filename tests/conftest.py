"""Shared fixtures: overhead views of the canonical 23-keypoint airliner."""

import numpy as np
import pytest

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.pose.geometry import project_batch

IMAGE_SIZE = (640, 400)  # width, height (the paper's 1920×1200 aspect)
HEATMAP_SCALE = (64 / 640, 64 / 400)  # image → 64×64 CNN heatmap


@pytest.fixture(scope="session")
def P():
    return airliner_keypoints()


@pytest.fixture(scope="session")
def K():
    return intrinsics(*IMAGE_SIZE, hfov_deg=70.0)


def views(n, seed, K, P, noise_px=0.0):
    """``n`` overhead views: poses (R, t) and keypoints V (n, 23, 2) with Gaussian noise."""
    R, t = overhead_poses(n, seed)
    V = project_batch(P, R, t, K)
    if noise_px:
        V = V + np.random.default_rng(seed + 1).normal(0.0, noise_px, V.shape)
    return R, t, V


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A rendered 20-image dataset at 160×100 (16 train, 2 val, 2 test images)."""
    from data_gen.dataset import generate_dataset

    return generate_dataset(
        tmp_path_factory.mktemp("tiny") / "data", 20, "160x100", seed=5, progress=False
    )
