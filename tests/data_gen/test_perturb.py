"""Perturbation sets: each perturbed image differs from its seed exactly where it should."""

import hashlib
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from data_gen.cli import main as data_gen_main
from data_gen.dataset import generate_dataset, load_coco, read_image
from data_gen.perturb import (
    PATCH_PX_AT_1920,
    apply_global,
    hull_vertices,
    load_perturbations,
    make_perturbations,
)
from kpstudy.models.preprocess import resize_to_input


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = generate_dataset(
        tmp_path_factory.mktemp("pt") / "data", 10, "320x200", seed=1, progress=False
    )
    make_perturbations(root, "objects", seeds=1, per_seed=12, seed=2)
    make_perturbations(root, "blocks", seeds=1, seed=2, input_size=32)
    make_perturbations(root, "brightness", seeds=1, input_size=32)
    make_perturbations(root, "contrast", seeds=1, input_size=32, levels=[5e-4, 1e-2])
    return root


def test_objects_change_only_the_patch_and_flag_overlap_from_the_mask(data):
    meta = load_perturbations(data, "objects")["images"]
    assert len(meta) == 12
    image = next(im for im in load_coco(data)["images"] if im["id"] == meta[0]["image_id"])
    seed = read_image(data / image["file_name"])
    mask = cv2.imread(str(data / image["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
    cap = PATCH_PX_AT_1920 * 320 / 1920
    for row in meta:
        perturbed = read_image(data / "perturbations/objects" / row["file"])
        changed = np.any(perturbed != seed, axis=2)
        (x, y), (w, h) = row["top_left"], row["patch_size"]
        inside = np.zeros_like(changed)
        inside[y : y + h, x : x + w] = True
        assert changed.any() and not np.any(changed & ~inside)
        assert max(w, h) <= cap
        # Overlapping iff the patch's alpha meets the mask: a changed airplane pixel implies it,
        # and an overlapping patch's box meets the mask (faint shadow alpha may round away).
        if np.any(changed & mask):
            assert row["overlapping"]
        if row["overlapping"]:
            assert np.any(inside & mask)
    assert len({row["occluder"] for row in meta}) > 3


def test_blocks_change_a_three_by_three_block_off_or_on_the_airplane(data):
    meta = load_perturbations(data, "blocks")["images"]
    assert sum(r["overlapping"] for r in meta) == 4 and len(meta) == 8
    for row in meta:
        vertices = hull_vertices(data, row["image_id"], "blocks", 4, row["overlapping"])
        assert vertices.shape == (5, 32, 32, 3)
        perturbed = np.load(data / "perturbations/blocks" / row["file"])
        changed = np.argwhere(np.any(perturbed != vertices[0], axis=2))
        x, y = row["top_left"]
        assert np.all((changed[:, 0] >= y) & (changed[:, 0] < y + 3))
        assert np.all((changed[:, 1] >= x) & (changed[:, 1] < x + 3))
        block = perturbed[y : y + 3, x : x + 3]
        assert np.all(block == np.rint(block)) and block.min() >= 0 and block.max() <= 255
        assert row["touches_airplane"] == row["overlapping"]


def test_global_vertices_change_every_unclipped_pixel(data):
    coco = load_coco(data)
    meta = load_perturbations(data, "brightness")["images"]
    image_id = meta[0]["image_id"]
    image = next(im for im in coco["images"] if im["id"] == image_id)
    seed = resize_to_input(read_image(data / image["file_name"]), 32)
    for level in (1.0, 2.0):
        vertices = hull_vertices(data, image_id, "brightness", level=level)
        assert vertices.shape == (3, 32, 32, 3)
        np.testing.assert_array_equal(vertices[0], seed)
        np.testing.assert_allclose(vertices[1], np.clip(seed + level, 0, 255))
        np.testing.assert_allclose(vertices[2], np.clip(seed - level, 0, 255))
        for vertex in vertices[1:]:
            free = (seed > level) & (seed < 255 - level)
            assert np.all(vertex[free] != seed[free])
    contrast = hull_vertices(data, image_id, "contrast", 2, level=5e-4)
    moved = contrast[1] != contrast[0]
    assert moved[contrast[0] > 0].mean() > 0.99  # a 0.05 % contrast change survives in float32
    fractions = [r["clipped_fraction"] for r in load_perturbations(data, "contrast")["images"]]
    assert all(0 <= f <= 1 for f in fractions)


def test_clipped_fraction_counts_saturated_values():
    image = np.array([[[0.0, 100.0, 254.5]]], np.float32)
    np.testing.assert_array_equal(apply_global(image, "brightness", 1.0), [[[1.0, 101.0, 255.0]]])
    np.testing.assert_array_equal(apply_global(image, "contrast", -0.5), [[[0.0, 50.0, 127.25]]])
    with pytest.raises(ValueError, match="kind"):
        apply_global(image, "gamma", 1.0)


def test_hull_vertices_objects_and_errors(data):
    meta = load_perturbations(data, "objects")["images"]
    image_id = meta[0]["image_id"]
    flags = [r["overlapping"] for r in meta]
    flag = max(set(flags), key=flags.count)
    vertices = hull_vertices(data, image_id, "objects", 2, flag, seed=0)
    assert vertices.shape == (3, 200, 320, 3) and vertices.dtype == np.float32
    assert not np.array_equal(vertices[1], vertices[2])
    np.testing.assert_array_equal(
        hull_vertices(data, image_id, "objects", 2, flag, seed=0), vertices
    )
    with pytest.raises(ValueError, match="m: expected 1.."):
        hull_vertices(data, image_id, "objects", 99, flag)
    with pytest.raises(ValueError, match="overlapping"):
        hull_vertices(data, image_id, "objects", 2)
    with pytest.raises(ValueError, match="image_id"):
        hull_vertices(data, -5, "objects", 2, flag)
    with pytest.raises(ValueError, match="level"):
        hull_vertices(data, image_id, "brightness", level=7.0)
    with pytest.raises(ValueError, match="level"):
        hull_vertices(data, image_id, "brightness")  # two levels stored: which one?
    with pytest.raises(ValueError, match="m: a brightness hull has 2"):
        hull_vertices(data, image_id, "brightness", 3, level=1.0)


def test_perturb_cli_errors(data, tmp_path):
    def run(*args):
        return subprocess.run(
            [sys.executable, "-m", "data_gen", "perturb", *args], capture_output=True, text=True
        )

    bad_kind = run("--data", str(data), "--kind", "fog")
    assert bad_kind.returncode == 2 and "kind: unknown perturbation 'fog'" in bad_kind.stderr
    missing = run("--data", str(tmp_path / "nowhere"), "--kind", "blocks")
    assert missing.returncode == 2 and "data_dir: no dataset" in missing.stderr
    again = run("--data", str(data), "--kind", "blocks", "--seeds", "1", "--input-size", "32")
    assert again.returncode == 2 and "--overwrite" in again.stderr
    too_many = run("--data", str(data), "--kind", "contrast", "--seeds", "50", "--overwrite")
    assert too_many.returncode == 2 and "seeds: asked for 50" in too_many.stderr
    assert load_perturbations(data, "contrast")["config"]["levels"] == [5e-4, 1e-2]  # untouched


# The tiny dataset's objects set (seeds=2, per_seed=4, seed=0) as the code before
# ``overlapping_share`` wrote it: sha256 of meta.json, and of the decoded pixels in row order.
DEFAULT_OBJECTS_META = "2db583d8e19e920e1b1e4830c4465c850dabe3dd227e8f4d7ffe7ffd925f9baf"

DEFAULT_OBJECTS_PIXELS = "993e590d5c5c1617fd7b64d83bde2ead348964c8db13c2bb081a51fdb05be7c6"


def test_objects_overlapping_share_centres_patches_on_the_airplane(tiny_dataset, tmp_path):
    data = shutil.copytree(tiny_dataset, tmp_path / "data")
    folder = data / "perturbations/objects"
    make_perturbations(data, "objects", seeds=2, per_seed=4, seed=0)
    default = load_perturbations(data, "objects")
    assert "overlapping_share" not in default["config"]
    assert all("aimed" not in row for row in default["images"])
    pixels = {row["file"]: read_image(folder / row["file"]) for row in default["images"]}
    digest = hashlib.sha256(b"".join(p.tobytes() for p in pixels.values())).hexdigest()
    meta_digest = hashlib.sha256((folder / "meta.json").read_bytes()).hexdigest()
    assert (meta_digest, digest) == (DEFAULT_OBJECTS_META, DEFAULT_OBJECTS_PIXELS)

    args = ["perturb", "--data", str(data), "--kind", "objects", "--seeds", "2"]
    args += ["--per-seed", "4", "--overlapping-share", "0.5", "--overwrite"]
    assert data_gen_main(args) == 0
    shared = load_perturbations(data, "objects")
    assert shared["config"] == default["config"] | {"overlapping_share": 0.5}
    images = {im["id"]: im for im in load_coco(data)["images"]}
    for image_id in shared["config"]["ids"]:
        rows = [r for r in shared["images"] if r["image_id"] == image_id]
        assert [r["aimed"] for r in rows] == [True, True, False, False]
        assert np.mean([r["overlapping"] for r in rows]) >= 0.5
        mask = cv2.imread(str(data / images[image_id]["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
        for row in rows:
            perturbed = read_image(folder / row["file"])
            if row["aimed"]:  # centred on an airplane pixel: the patch's box meets the mask
                (x, y), (w, h) = row["top_left"], row["patch_size"]
                assert mask[y : y + h, x : x + w].any()
            else:  # the same draws as the default set's
                np.testing.assert_array_equal(perturbed, pixels[row["file"]])


@pytest.mark.parametrize("share", [1.5, -0.1, float("nan"), True, "0.5"])
def test_overlapping_share_refused(tiny_dataset, share):
    with pytest.raises(ValueError, match=r"^overlapping_share: expected a number in \[0, 1\]"):
        make_perturbations(tiny_dataset, "objects", seeds=1, overlapping_share=share)
    assert not list(tiny_dataset.glob("perturbations/*objects*"))  # nor .objects.partial


def test_overlapping_share_refused_for_other_kinds_and_on_the_cli(tiny_dataset, capsys):
    with pytest.raises(ValueError, match="^overlapping_share: applies to objects only"):
        make_perturbations(tiny_dataset, "blocks", seeds=1, overlapping_share=0.5)
    args = ["perturb", "--data", str(tiny_dataset), "--kind", "objects", "--seeds", "1"]
    with pytest.raises(SystemExit) as exit_:
        data_gen_main([*args, "--overlapping-share", "2"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err == (
        "data_gen perturb: error: overlapping_share: expected a number in [0, 1] or None, got 2.0\n"
    )
    assert not list(tiny_dataset.glob("perturbations/*objects*"))  # nor .objects.partial
