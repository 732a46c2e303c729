"""Shared fixtures: overhead views of the canonical 23-keypoint airliner, a rendered tiny
dataset, and a tiny trained study on it (``study``)."""

import shutil

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


@pytest.fixture(scope="module")
def study(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset with block and brightness perturbations, and a CNN
    trained on it for two epochs: ``(data, checkpoint)``. One per test module."""
    from data_gen.perturb import make_perturbations
    from kpstudy.models.training import TrainConfig, train

    data = tmp_path_factory.mktemp("study") / "data"
    shutil.copytree(tiny_dataset, data)
    for kind in ("blocks", "brightness"):
        make_perturbations(data, kind, seeds=2, seed=0, input_size=64)
    checkpoint = data.parent / "cnn.pt"
    train(data, checkpoint, TrainConfig(epochs=2, batch_size=4, images=8, seed=1), progress=False)
    return data, checkpoint


def seed_image(data_dir, index=0):
    """Test image ``index`` of the dataset at ``data_dir`` as a seed image (64 px input)."""
    from kpstudy.certify.allocation_method import SeedImage
    from kpstudy.models.data import load_keypoint_set

    return SeedImage.from_keypoint_set(load_keypoint_set(data_dir, "test", 64), index)
