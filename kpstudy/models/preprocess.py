"""Preprocessing F0: an image → the network's input, and pixels ↔ input pixels.

The whole image is resized to the model input (64×64 for the CNN, 256×256 for
ResNet-18) by pixel-area averaging, a linear map: the resized convex hull of images
is the convex hull of the resized images. Values stay in [0, 255] until
:func:`to_model_input`, the one step from images to the network's input tensor. A
resize by factors ``(sx, sy)`` maps pixel coordinates as ``u' = (u + 0.5)·sx − 0.5``
(docs/design.md §3).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch


def _size(size) -> tuple[int, int]:
    width, height = (int(s) for s in (size, size)) if np.isscalar(size) else (int(s) for s in size)
    if width < 1 or height < 1:
        raise ValueError(f"size: expected a positive input size, got {size}")
    return width, height


def resize_to_input(image: np.ndarray, size) -> np.ndarray:
    """Resize an image (H, W, 3), uint8 or float in [0, 255], to (h, w, 3) float32.

    ``size`` is ``s`` (square) or ``(w, h)``. Area averaging (``cv2.INTER_AREA``).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected an (H, W, 3) image, got shape {image.shape}")
    width, height = _size(size)
    return cv2.resize(image.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)


def scale_factors(image_size, input_size) -> tuple[float, float]:
    """Resize factors ``(sx, sy)`` from an image of ``(W, H)`` to an input of ``(w, h)``."""
    (W, H), (w, h) = _size(image_size), _size(input_size)
    return w / W, h / H


def to_input_pixels(uv: np.ndarray, factors) -> np.ndarray:
    """Image pixel coordinates (..., 2) → input pixel coordinates (..., 2)."""
    return (np.asarray(uv, float) + 0.5) * np.asarray(factors, float) - 0.5


def to_image_pixels(uv: np.ndarray, factors) -> np.ndarray:
    """Input pixel coordinates (..., 2) → image pixel coordinates (..., 2)."""
    return (np.asarray(uv, float) + 0.5) / np.asarray(factors, float) - 0.5


def to_model_input(images, size=None) -> torch.Tensor:
    """Images ``(N, H, W, 3)`` in [0, 255] (uint8 or float) → the network's input
    ``(N, 3, h, w)``: float32 in [0, 1], contiguous.

    With ``size`` (``s`` or ``(w, h)``) each image is first resized to it
    (:func:`resize_to_input`); without, the images must already have the input size.

    >>> to_model_input(np.full((2, 4, 6, 3), 255, np.uint8), size=2).shape
    torch.Size([2, 3, 2, 2])
    """
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected (N, H, W, 3) images, got shape {images.shape}")
    if size is not None:
        images = np.stack([resize_to_input(image, size) for image in images])
    x = torch.from_numpy(np.asarray(images, np.float32) / np.float32(255.0))
    return x.permute(0, 3, 1, 2).contiguous()
