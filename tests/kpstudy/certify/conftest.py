"""Fixtures of the certify tests: the pose-bound tests' scene (a seed image of the airliner,
its pose and its keypoints on the 64 × 64 heatmap)."""

import numpy as np
import pytest

from kpstudy.certify.allocation_method import SeedImage
from kpstudy.models.preprocess import scale_factors, to_input_pixels
from tests.conftest import IMAGE_SIZE, views
from tests.helpers.pose_bound import HM


@pytest.fixture(scope="module")
def scene(P, K):
    """A seed image (exact keypoints), its nominal pose and the rounded heatmap pixels."""
    R, t, V = views(1, 3, K, P)
    seed = SeedImage(0, V[0], K, P, IMAGE_SIZE)
    factors = scale_factors(IMAGE_SIZE, HM)
    centers = np.clip(np.rint(to_input_pixels(V[0], factors)), 0, HM - 1)
    return seed, R[0], t[0], factors, centers
