"""kpstudy.models.data: the keypoint set is preprocessing f0 of the rendered dataset;
bad arguments and a NaN keypoint (issue 29, point 5) are refused by name."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from kpstudy.models.data import load_keypoint_set
from kpstudy.models.preprocess import resize_to_input, scale_factors, to_input_pixels
from kpstudy.models.training import TrainConfig, train


def test_keypoint_set_is_preprocessing_f0(tiny_dataset):
    from data_gen.dataset import read_image

    data = load_keypoint_set(tiny_dataset, "train", 64)
    assert data.images.shape == (16, 64, 64, 3) and data.images.dtype == np.float32
    assert data.keypoints.shape == (16, 23, 2) and data.image_size == (160, 100)
    first = read_image(tiny_dataset / "images" / f"{data.image_ids[0]:06d}.png")
    np.testing.assert_array_equal(data.images[0], resize_to_input(first, 64))
    factors = scale_factors((160, 100), 64)
    np.testing.assert_allclose(data.keypoints, to_input_pixels(data.image_keypoints, factors))
    np.testing.assert_allclose(data.to_image_pixels(data.keypoints), data.image_keypoints)
    assert len(load_keypoint_set(tiny_dataset, "test", 64, limit=1)) == 1


@pytest.mark.parametrize(
    "args, error, message",
    [
        (("nowhere", "train", 64), FileNotFoundError, "data: no dataset folder"),
        ((None, "dev", 64), ValueError, "split: expected one of"),
        ((None, "train", 0), ValueError, "input_size: expected a positive integer"),
    ],
)
def test_keypoint_set_bad_input(tiny_dataset, args, error, message):
    args = (tiny_dataset if args[0] is None else args[0], *args[1:])
    with pytest.raises(error, match=message):
        load_keypoint_set(*args)


SHORT = TrainConfig(epochs=2, batch_size=4, images=8, seed=1)  # 2 steps per epoch


@pytest.fixture
def nan_dataset(tiny_dataset, tmp_path):
    """The tiny dataset with one NaN coordinate in the first training image's keypoints."""
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    coco = json.loads((data / "annotations.json").read_text())
    image = next(im for im in coco["images"] if im["split"] == "train")
    annotation = next(a for a in coco["annotations"] if a["image_id"] == image["id"])
    annotation["keypoints"][3] = math.nan  # keypoint 1's u
    (data / "annotations.json").write_text(json.dumps(coco))
    return data, image["file_name"]


def test_a_nan_keypoint_is_refused_at_load_naming_the_image(nan_dataset, tmp_path):
    data, file_name = nan_dataset
    with pytest.raises(ValueError, match=f"^data: image '{file_name}' .*non-finite keypoints"):
        load_keypoint_set(data, "train", 64)
    with pytest.raises(ValueError, match="non-finite keypoints"):
        train(data, tmp_path / "c.pt", SHORT, progress=False)
    assert not (tmp_path / "c.pt").exists()
