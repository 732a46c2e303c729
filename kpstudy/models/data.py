"""data_gen's COCO keypoint dataset as network inputs, keypoint labels and poses.

Images go through preprocessing F0 (:mod:`kpstudy.models.preprocess`): the whole image is
resized to the square model input, values stay in [0, 255] (``normalise`` divides by 255
when a batch enters a network). Keypoints are converted to the heatmap's pixels with the
resize factors (docs/design.md §3); the backbones' heatmaps have the input's size.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kpstudy import _checks
from kpstudy.models.preprocess import (
    resize_to_input,
    scale_factors,
    to_image_pixels,
    to_input_pixels,
)

#: The dataset's splits, the names :func:`load_keypoint_set` takes.
SPLITS = ("train", "val", "test")


@dataclass
class KeypointSet:
    """One split of a keypoint dataset at one input size (N images, K keypoints).

    Attributes
    ----------
    images : ndarray, (N, s, s, 3) float32
        Preprocessed images in [0, 255].
    keypoints : ndarray, (N, K, 2) float64
        Ground-truth ``(u, v)`` in heatmap (= input) pixels.
    visibility : ndarray, (N, K) int
        COCO flags: 0 outside the image, 1 hidden, 2 visible.
    image_keypoints : ndarray, (N, K, 2) float64
        Ground-truth ``(u, v)`` in image pixels.
    K, R, t : ndarray, (N, 3, 3), (N, 3, 3), (N, 3)
        Intrinsics and ground-truth pose (object → camera, metres).
    points_3d : ndarray, (K, 3)
        The keypoints in the object frame (metres).
    image_ids : ndarray, (N,) int
    image_size : (int, int)
        ``(W, H)`` of the rendered images.
    input_size : int
    keypoint_names : list of str
    """

    images: np.ndarray
    keypoints: np.ndarray
    visibility: np.ndarray
    image_keypoints: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points_3d: np.ndarray
    image_ids: np.ndarray
    image_size: tuple[int, int]
    input_size: int
    keypoint_names: list[str]

    def __len__(self) -> int:
        return len(self.images)

    @property
    def scale(self) -> tuple[float, float]:
        """Resize factors ``(sx, sy)`` from image to heatmap pixels."""
        return scale_factors(self.image_size, self.input_size)

    def to_image_pixels(self, uv) -> np.ndarray:
        """Heatmap pixel coordinates (..., 2) → image pixel coordinates (..., 2)."""
        return to_image_pixels(uv, self.scale)


def load_keypoint_set(data_dir, split: str, input_size: int, *, limit=None) -> KeypointSet:
    """Read one split of data_gen's dataset at ``data_dir`` and preprocess its images.

    Parameters
    ----------
    data_dir : path
        A folder written by ``python -m data_gen dataset``.
    split : {'train', 'val', 'test'}
    input_size : int
        Side of the square model input (64 for the CNN, 256 for ResNet-18).
    limit : int, optional
        Keep the first ``limit`` images of the split.

    Raises
    ------
    ValueError
        Bad arguments, or a dataset that is not data_gen's or holds non-finite numbers
        (keypoints, intrinsics or pose of an image, which is named; the 3-D keypoints).
    """
    from data_gen.dataset import load_coco, read_image

    _checks.choice(split, "split", SPLITS)
    _checks.integer(input_size, "input_size", minimum=1)
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"data: no dataset folder at {data_dir}")
    coco = load_coco(data_dir)
    try:
        category = coco["categories"][0]
        by_image = {a["image_id"]: a for a in coco["annotations"]}
        images = [im for im in coco["images"] if im["split"] == split][:limit]
        sizes = {(im["width"], im["height"]) for im in images}
        if not images:
            raise ValueError(f"split: the dataset at {data_dir} has no {split!r} images")
        if len(sizes) != 1:
            raise ValueError(f"data: expected one image size, got {sorted(sizes)}")
        names = list(category["keypoints"])
        points_3d = np.asarray(category["keypoints_3d"], float)
        kps = np.array([by_image[im["id"]]["keypoints"] for im in images], float)
        kps = kps.reshape(len(images), len(names), 3)
        poses = [by_image[im["id"]]["pose"] for im in images]
        K = np.array([im["K"] for im in images], float)
        R = np.array([p["R"] for p in poses], float)
        t = np.array([p["t"] for p in poses], float)
    except (KeyError, IndexError, TypeError) as exc:
        raise ValueError(f"data: {data_dir} is not a data_gen keypoint dataset ({exc!r})") from exc
    _check_finite(data_dir, images, kps, K, R, t, points_3d)
    image_size = sizes.pop()

    def load(im):
        return resize_to_input(read_image(data_dir / im["file_name"]), input_size)

    with ThreadPoolExecutor(2) as pool:
        pixels = np.stack(list(pool.map(load, images)))
    uv = kps[..., :2]
    return KeypointSet(
        images=pixels,
        keypoints=to_input_pixels(uv, scale_factors(image_size, input_size)),
        visibility=kps[..., 2].astype(int),
        image_keypoints=uv,
        K=K,
        R=R,
        t=t,
        points_3d=points_3d,
        image_ids=np.array([im["id"] for im in images]),
        image_size=image_size,
        input_size=input_size,
        keypoint_names=names,
    )


def _check_finite(data_dir, images, kps, K, R, t, points_3d) -> None:
    """Refuse NaN or inf in the annotations, naming the first image that holds one."""
    if points_3d.ndim != 2 or points_3d.shape[1:] != (3,) or not np.isfinite(points_3d).all():
        raise ValueError(
            f"data: expected finite 3-D keypoints (K, 3) in the category of {data_dir}"
        )
    checks = (
        ("keypoints", kps.reshape(len(images), -1)),
        ("intrinsics K", K.reshape(len(images), -1)),
        ("pose R", R.reshape(len(images), -1)),
        ("pose t", t.reshape(len(images), -1)),
    )
    for what, values in checks:
        bad = np.flatnonzero(~np.isfinite(values).all(1))
        if bad.size:
            im = images[bad[0]]
            raise ValueError(
                f"data: image {im['file_name']!r} (id {im['id']}) of {data_dir} has non-finite "
                f"{what} (NaN or inf); expected finite annotations"
            )
