"""kpstudy.models.preprocess, preprocessing F0: the resize is pixel-area averaging, a linear
map; pixel coordinates map between image and input with the pixel edges aligned; the
network's input is float32 in [0, 1], channels first."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kpstudy.models.preprocess import (
    resize_to_input,
    scale_factors,
    to_image_pixels,
    to_input_pixels,
    to_model_input,
)


def test_the_resize_averages_pixel_areas_and_is_linear():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 255, (4, 9, 3))  # 2 × 3 areas of 2 × 3 pixels
    small = resize_to_input(image, (3, 2))  # (w, h)
    assert small.shape == (2, 3, 3) and small.dtype == np.float32
    means = image.reshape(2, 2, 3, 3, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(small, means, rtol=1e-5, atol=1e-3)
    other = rng.uniform(0, 255, image.shape)
    mixed = resize_to_input(0.25 * image + 0.75 * other, (3, 2))
    want = 0.25 * small + 0.75 * resize_to_input(other, (3, 2))
    np.testing.assert_allclose(mixed, want, rtol=1e-5, atol=1e-3)  # hulls resize to hulls
    flat = resize_to_input(np.full((40, 64, 3), 7, np.uint8), 16)
    assert flat.shape == (16, 16, 3) and np.all(flat == 7)


def test_pixel_coordinates_keep_pixel_edges_and_centres_aligned():
    factors = scale_factors((640, 400), 64)
    assert factors == (0.1, 0.16)
    # Image pixels 0…9 (u) and 0…6.25 (v) fall in input pixel 0: their centre is its centre.
    np.testing.assert_allclose(to_input_pixels([4.5, 2.625], factors), [0.0, 0.0])
    np.testing.assert_allclose(to_input_pixels([-0.5, -0.5], factors), [-0.5, -0.5])
    np.testing.assert_allclose(to_input_pixels([639.5, 399.5], factors), [63.5, 63.5])
    uv = np.random.default_rng(1).uniform(0, 600, (5, 23, 2))
    np.testing.assert_allclose(to_image_pixels(to_input_pixels(uv, factors), factors), uv)
    assert scale_factors(256, (1024, 512)) == (4.0, 2.0)


def test_the_model_input_is_float32_in_the_unit_range_channels_first():
    images = np.zeros((2, 4, 6, 3), np.uint8)
    images[1, 2, 5] = (255, 51, 0)
    x = to_model_input(images)
    assert x.shape == (2, 3, 4, 6) and x.dtype == torch.float32 and x.is_contiguous()
    assert x[1, :, 2, 5].tolist() == pytest.approx([1.0, 0.2, 0.0])
    assert x.sum() == pytest.approx(1.2)
    resized = to_model_input(np.full((1, 40, 60, 3), 255.0), size=(6, 4))
    assert resized.shape == (1, 3, 4, 6) and torch.all(resized == 1.0)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: resize_to_input(np.zeros((4, 4)), 2), r"^image: expected an \(H, W, 3\) image"),
        (lambda: resize_to_input(np.zeros((4, 4, 3)), 0), "^size: expected a positive"),
        (lambda: scale_factors((640, 0), 64), "^size: expected a positive"),
        (lambda: to_model_input(np.zeros((4, 4, 3))), r"^images: expected \(N, H, W, 3\)"),
        (lambda: to_model_input(np.zeros((1, 4, 4, 4))), r"^images: expected \(N, H, W, 3\)"),
    ],
)
def test_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()
