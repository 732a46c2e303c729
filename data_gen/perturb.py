"""The study's perturbation sets (paper §8.1, docs/design.md §5) and the convex hulls they give.

``make_perturbations(data_dir, kind, …)`` writes ``data_dir/perturbations/<kind>/``
with ``meta.json`` and one file per perturbed image, for seed images drawn from the
test split:

- ``objects``: per seed image ``per_seed`` (20) images, each with one occluder patch
  (rendered top-down at the image's ground scale under its light, with its cast
  shadow) at a random place, drawn among the occluders whose patch side at the
  image's true ground scale is 8–150 px at 1920 px image width (scaled with the
  width). ``overlapping`` iff the patch's alpha meets the airplane mask. Stored as
  PNG at the render's resolution. With ``overlapping_share`` s, the first
  ``round(s · per_seed)`` patches of each seed image are centred on a pixel drawn
  uniformly among the airplane-mask pixels (so that enough of them overlap for the
  overlapping hulls), the rest at random places as before; ``overlapping`` is still
  read from the patch's alpha and the mask.
- ``blocks``: in model-input space (``input_size``), per seed image 4 images with a
  3×3 block of uniform random values in [0, 255] away from the airplane
  (non-overlapping) and 4 with the block centred on a random visible keypoint
  (overlapping).
- ``brightness`` / ``contrast``: in model-input space, per level the vertices
  ``clip(I ± b)`` / ``clip(I·(1 ± c))``, with the fraction of clipped values recorded
  (clipping is why the hull misses some intermediate images).

Model-input images are :func:`kpstudy.models.preprocess.resize_to_input` of the render,
stored as float32 ``.npy`` in [0, 255] (a contrast of 5e-4 would vanish in uint8),
together with the resized seed image.

``hull_vertices(data_dir, image_id, kind, m, overlapping, seed)`` returns the seed and
``m`` perturbed images of one seed image: the vertices of a convex hull.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from data_gen.dataset import check_seed, load_coco, read_image, read_json, write_png
from data_gen.occluders import occluder_catalog
from data_gen.patches import PatchRenderer, paste, patch_light
from data_gen.scene import SceneParams
from kpstudy.io import check_output_dir, staged_directory, write_bytes_atomic, write_text_atomic
from kpstudy.models.preprocess import resize_to_input, scale_factors, to_input_pixels

KINDS = ("objects", "blocks", "brightness", "contrast")
DEFAULT_LEVELS = {"brightness": (1.0, 2.0), "contrast": (5e-4, 5e-3, 1e-2)}
PATCH_PX_AT_1920 = 150  # the paper's largest patch side at 1920 px image width
MIN_PATCH_PX_AT_1920 = 8  # smaller occluders (a person far below) would barely change a pixel
BLOCK = 3


def seed_images(coco: dict, count: int | None, seed: int) -> list[int]:
    """Ids of ``count`` test-split images drawn with ``seed`` (all test images if None), sorted."""
    test = sorted(im["id"] for im in coco["images"] if im.get("split") == "test")
    if not test:
        raise ValueError("data_dir: the dataset has no test images to perturb")
    if count is None:
        return test
    if isinstance(count, bool) or int(count) != count or count < 1:
        raise ValueError(f"seeds: expected a positive number of seed images, got {count}")
    if count > len(test):
        raise ValueError(f"seeds: asked for {count} seed images, the test split has {len(test)}")
    rng = np.random.default_rng([seed, 1])
    return sorted(int(i) for i in rng.choice(test, size=int(count), replace=False))


def _ground_scale(u: float, v: float, image: dict, ground_z: float) -> float:
    """Pixels per metre on the ground plane at pixel (u, v)."""
    K = np.asarray(image["K"])
    R, t = (np.asarray(image["pose"][k]) for k in ("R", "t"))
    ray = np.linalg.solve(K, [u, v, 1.0])
    normal = R[:, 2]  # ground normal in the camera frame
    depth = (ground_z + normal @ t) / (normal @ ray)  # camera z of the ground point
    return float(K[0, 0] / depth)


def _objects(
    data_dir: Path,
    coco: dict,
    ids: list[int],
    staging: Path,
    per_seed: int,
    seed: int,
    share: float | None = None,
) -> list[dict]:
    aimed_count = 0 if share is None else round(share * per_seed)
    images = {im["id"]: im for im in coco["images"]}
    poses = {a["image_id"]: a["pose"] for a in coco["annotations"]}
    ground_z = coco["categories"][0]["ground_z"]
    catalog = occluder_catalog()
    renderer = PatchRenderer()
    meta = []
    for image_id in tqdm(ids, desc="objects", unit="seed"):
        info = dict(images[image_id], pose=poses[image_id])
        picture = read_image(data_dir / info["file_name"])
        mask = cv2.imread(str(data_dir / info["mask_file"]), cv2.IMREAD_GRAYSCALE) > 0
        H, W = mask.shape
        airplane = np.argwhere(mask)[:, ::-1].astype(float)  # (u, v) of every mask pixel
        if aimed_count and not len(airplane):
            raise RuntimeError(
                f"objects: image {image_id} has no airplane pixel to centre a patch on "
                "(overlapping_share)"
            )
        cap = max(int(round(PATCH_PX_AT_1920 * W / 1920)), 4)
        least = max(int(round(MIN_PATCH_PX_AT_1920 * W / 1920)), 3)
        light = patch_light(
            SceneParams(**_tuples(info["scene"])).light(), np.asarray(info["pose"]["R"])
        )
        for k in range(per_seed):
            rng = np.random.default_rng([seed, image_id, k])
            aimed = k < aimed_count
            for _ in range(100):
                occluder = catalog[rng.integers(len(catalog))]
                if aimed:
                    centre = airplane[rng.integers(len(airplane))]
                else:
                    centre = rng.uniform((0, 0), (W - 1, H - 1))
                scale = _ground_scale(*centre, info, ground_z)
                if not least <= max(occluder.mesh.extents[:2]) * scale <= cap:
                    continue
                yaw = float(rng.uniform(0, 360))
                patch = renderer.render(occluder.name, occluder.mesh, scale, light, yaw)
                h, w = patch.shape[:2]
                if least <= max(h, w) <= cap:
                    break
            else:
                raise RuntimeError(
                    f"objects: no occluder spans {least}–{cap} px on image {image_id}"
                )
            x = int(np.clip(round(centre[0] - w / 2), 0, W - w))
            y = int(np.clip(round(centre[1] - h / 2), 0, H - h))
            perturbed, alpha = paste(picture, patch, (x, y))
            name = f"{image_id:06d}_{k:02d}.png"
            write_png(staging / name, perturbed)
            row = {
                "image_id": image_id,
                "file": name,
                "overlapping": bool(np.any((alpha > 0) & mask)),
                "occluder": occluder.name,
                "family": occluder.family,
                "yaw_deg": yaw,
                "px_per_m": scale,
                "top_left": [x, y],
                "patch_size": [w, h],
            }
            if share is not None:  # rows of the default sets stay as they were
                row["aimed"] = aimed  # centre drawn among the airplane-mask pixels
            meta.append(row)
    return meta


def _input_seed(data_dir: Path, info: dict, input_size, staging: Path) -> tuple[np.ndarray, str]:
    seed_image = resize_to_input(read_image(data_dir / info["file_name"]), input_size)
    name = f"{info['id']:06d}_seed.npy"
    _write_npy(staging / name, seed_image)
    return seed_image, name


def _blocks(data_dir, coco, ids, staging, per_seed, seed, input_size) -> list[dict]:
    images = {im["id"]: im for im in coco["images"]}
    keypoints = {a["image_id"]: np.reshape(a["keypoints"], (-1, 3)) for a in coco["annotations"]}
    meta = []
    for image_id in tqdm(ids, desc="blocks", unit="seed"):
        info = images[image_id]
        seed_image, seed_name = _input_seed(data_dir, info, input_size, staging)
        h, w = seed_image.shape[:2]
        mask = cv2.imread(str(data_dir / info["mask_file"]), cv2.IMREAD_GRAYSCALE).astype(
            np.float32
        )
        airplane = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA) > 0
        # Top-left corners whose block stays clear of the airplane (and inside the image).
        touched = np.lib.stride_tricks.sliding_window_view(airplane, (BLOCK, BLOCK)).any(
            axis=(2, 3)
        )
        free = np.argwhere(~touched)
        kp = keypoints[image_id]
        centres = to_input_pixels(
            kp[kp[:, 2] == 2, :2], scale_factors((info["width"], info["height"]), (w, h))
        )
        for overlapping in (False, True):
            for k in range(per_seed):
                rng = np.random.default_rng([seed, image_id, int(overlapping), k])
                if overlapping:
                    cu, cv = np.rint(centres[rng.integers(len(centres))]).astype(int)
                    y, x = int(np.clip(cv - 1, 0, h - BLOCK)), int(np.clip(cu - 1, 0, w - BLOCK))
                else:
                    if len(free) == 0:
                        raise RuntimeError(
                            f"blocks: image {image_id} has no room for a block off the airplane"
                        )
                    y, x = (int(a) for a in free[rng.integers(len(free))])
                perturbed = seed_image.copy()
                perturbed[y : y + BLOCK, x : x + BLOCK] = rng.integers(0, 256, (BLOCK, BLOCK, 3))
                name = f"{image_id:06d}_{'on' if overlapping else 'off'}_{k}.npy"
                touches = bool(airplane[y : y + BLOCK, x : x + BLOCK].any())
                meta.append(
                    _save_input(staging, name, perturbed, image_id, seed_name,
                                overlapping=overlapping, top_left=[x, y], touches_airplane=touches)
                )  # fmt: skip
    return meta


def apply_global(image: np.ndarray, kind: str, value: float, clip: bool = True) -> np.ndarray:
    """``clip(I + value)`` (brightness) or ``clip(I·(1 + value))`` (contrast), I in [0, 255]."""
    if kind == "brightness":
        out = image + value
    elif kind == "contrast":
        out = image * (1 + value)
    else:
        raise ValueError(f"kind: expected 'brightness' or 'contrast', got {kind!r}")
    return (np.clip(out, 0, 255) if clip else out).astype(np.float32)


def _global(data_dir, coco, ids, staging, kind, levels, input_size) -> list[dict]:
    images = {im["id"]: im for im in coco["images"]}
    meta = []
    for image_id in tqdm(ids, desc=kind, unit="seed"):
        seed_image, seed_name = _input_seed(data_dir, images[image_id], input_size, staging)
        for level in levels:
            for sign in (1, -1):
                raw = apply_global(seed_image, kind, sign * level, clip=False)
                perturbed = np.clip(raw, 0, 255)
                name = f"{image_id:06d}_{level:g}_{'plus' if sign > 0 else 'minus'}.npy"
                clipped = float(np.mean((raw < 0) | (raw > 255)))
                meta.append(
                    _save_input(staging, name, perturbed, image_id, seed_name,
                                level=float(level), sign=sign, overlapping=None,
                                clipped_fraction=clipped)
                )  # fmt: skip
    return meta


def make_perturbations(
    data_dir,
    kind: str,
    *,
    seeds: int | None = 10,
    seed: int = 0,
    per_seed: int | None = None,
    input_size=64,
    levels=None,
    overwrite: bool = False,
    overlapping_share: float | None = None,
) -> Path:
    """Write one perturbation set into ``data_dir/perturbations/<kind>/`` (module docstring).

    Parameters
    ----------
    data_dir : path
        A dataset of :func:`data_gen.dataset.generate_dataset`.
    kind : {'objects', 'blocks', 'brightness', 'contrast'}
    seeds : int or None
        Number of seed images drawn from the test split (None: all of it).
    seed : int
        Seed of every draw (seed images, placements, values).
    per_seed : int, optional
        Perturbed images per seed image: 20 objects, 4 blocks of each kind by default.
    input_size : int or (int, int)
        Model-input size of the blocks and global perturbations (64 CNN, 256 ResNet-18).
    levels : sequence of float, optional
        Brightness b (defaults 1, 2) or contrast c (defaults 5e-4, 5e-3, 1e-2).
    overlapping_share : float in [0, 1], optional
        Objects only: the first ``round(overlapping_share · per_seed)`` (Python's
        ``round``) patches of each seed image are centred on a pixel drawn uniformly
        among its airplane-mask pixels, the rest anywhere in the image. None (default):
        all anywhere, the set unchanged. Recorded in ``meta.json``'s config (and each
        row's ``aimed``) only when given; ``overlapping`` stays alpha ∩ mask.

    Returns
    -------
    The folder written; it appears only when complete.
    """
    if kind not in KINDS:
        raise ValueError(f"kind: unknown perturbation {kind!r}; expected one of {', '.join(KINDS)}")
    seed = check_seed(seed)
    data_dir = Path(data_dir)
    coco = load_coco(data_dir)
    ids = seed_images(coco, seeds, seed)
    if per_seed is None:
        per_seed = 20 if kind == "objects" else 4
    if isinstance(per_seed, bool) or int(per_seed) != per_seed or per_seed < 1:
        raise ValueError(f"per_seed: expected a positive integer, got {per_seed}")
    if kind in DEFAULT_LEVELS:
        levels = DEFAULT_LEVELS[kind] if levels is None else tuple(float(v) for v in levels)
        if not levels or any(not np.isfinite(v) or v <= 0 for v in levels):
            raise ValueError(f"levels: expected positive {kind} levels, got {levels}")
    size = (
        (int(input_size), int(input_size))
        if np.isscalar(input_size)
        else tuple(int(s) for s in input_size)
    )
    if len(size) != 2 or min(size) < BLOCK:
        raise ValueError(f"input_size: expected a model-input size ≥ {BLOCK}, got {input_size}")
    share = _check_share(overlapping_share, kind)
    out = check_output_dir(data_dir / "perturbations" / kind, overwrite)
    config = {
        "kind": kind,
        "ids": ids,
        "seed": seed,
        "per_seed": int(per_seed),
        "input_size": list(size),
        "levels": levels,
    }
    if share is not None:  # the default set's config (and so its reuse) stays as it was
        config["overlapping_share"] = share
    with staged_directory(out, config) as (staging, _):
        if kind == "objects":
            meta = _objects(data_dir, coco, ids, staging, int(per_seed), seed, share)
        elif kind == "blocks":
            meta = _blocks(data_dir, coco, ids, staging, int(per_seed), seed, size)
        else:
            meta = _global(data_dir, coco, ids, staging, kind, levels, size)
        write_text_atomic(
            staging / "meta.json", json.dumps({"config": config, "images": meta}, indent=1)
        )
    return out


def _check_share(share, kind: str) -> float | None:
    """``overlapping_share`` as a float in [0, 1], or None; ValueError naming it."""
    if share is None:
        return None
    if (
        isinstance(share, (bool, np.bool_))
        or not isinstance(share, (int, float, np.integer, np.floating))
        or not 0 <= share <= 1  # NaN fails too
    ):
        raise ValueError(f"overlapping_share: expected a number in [0, 1] or None, got {share!r}")
    if kind != "objects":
        raise ValueError(f"overlapping_share: applies to objects only, not {kind}")
    return float(share)


def load_perturbations(data_dir, kind: str) -> dict:
    """``meta.json`` of a perturbation set; FileNotFoundError naming ``kind`` if absent."""
    if kind not in KINDS:
        raise ValueError(f"kind: unknown perturbation {kind!r}; expected one of {', '.join(KINDS)}")
    path = Path(data_dir) / "perturbations" / kind / "meta.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"kind: no {kind} perturbations in {data_dir} (run `python -m data_gen perturb`)"
        )
    return read_json(path, "kind")


def hull_vertices(
    data_dir,
    image_id: int,
    kind: str,
    m: int | None = None,
    overlapping: bool | None = None,
    seed: int = 0,
    *,
    level=None,
) -> np.ndarray:
    """The seed image and ``m`` perturbed images of it: a convex hull's vertices.

    Parameters
    ----------
    image_id : int
        A seed image of the set.
    kind : {'objects', 'blocks', 'brightness', 'contrast'}
    m : int
        Number of perturbed images (objects: ≤ the matching ones; blocks ≤ 4; the global
        kinds always have 2 and take ``m`` None or 2).
    overlapping : bool
        Objects and blocks: take only overlapping (True) or non-overlapping (False) images.
    seed : int
        Which ``m`` of the matching images (drawn without replacement).
    level : float, optional
        Brightness b or contrast c; needed when the set holds several.

    Returns
    -------
    ndarray (m + 1, H, W, 3) float32 in [0, 255]; row 0 is the seed image. Objects are at
    the render's resolution, the other kinds at the model-input size.
    """
    data_dir = Path(data_dir)
    meta = load_perturbations(data_dir, kind)
    rows = [r for r in meta["images"] if r["image_id"] == image_id]
    if not rows:
        raise ValueError(f"image_id: {image_id} is not a seed image of the {kind} set")
    folder = data_dir / "perturbations" / kind
    if kind in DEFAULT_LEVELS:
        stored = sorted({r["level"] for r in rows})
        if level is None and len(stored) == 1:
            level = stored[0]
        chosen = [r for r in rows if level is not None and np.isclose(r["level"], level)]
        if not chosen:
            raise ValueError(f"level: expected one of {stored} for {kind}, got {level}")
        if m not in (None, 2):
            raise ValueError(
                f"m: a {kind} hull has 2 perturbed images (+{level:g} and −{level:g}), got {m}"
            )
        chosen.sort(key=lambda r: -r["sign"])
    else:
        if overlapping is None:
            raise ValueError(f"overlapping: expected True or False for a {kind} hull")
        matching = [r for r in rows if r["overlapping"] == bool(overlapping)]
        if isinstance(m, bool) or m is None or int(m) != m or not 1 <= m <= len(matching):
            raise ValueError(
                f"m: expected 1..{len(matching)} "
                f"({'' if overlapping else 'non-'}overlapping {kind} images of "
                f"image {image_id}), got {m}"
            )
        pick = np.random.default_rng([seed, image_id]).choice(
            len(matching), size=int(m), replace=False
        )
        chosen = [matching[i] for i in sorted(pick)]
    if kind == "objects":
        coco_image = next(im for im in load_coco(data_dir)["images"] if im["id"] == image_id)
        first = read_image(data_dir / coco_image["file_name"]).astype(np.float32)
        rest = [read_image(folder / r["file"]).astype(np.float32) for r in chosen]
    else:
        first = np.load(folder / chosen[0]["seed_file"])
        rest = [np.load(folder / r["file"]) for r in chosen]
    return np.stack([first, *rest])


def perturbed_images(data_dir, kind: str, input_size: int, *, limit: int | None = None):
    """Every perturbed image of a set (at most ``limit``), resized to the model input.

    Returns ``(images (N, s, s, 3) float32 in [0, 255], rows)``, ``rows`` being the
    matching entries of ``meta.json`` (image id, overlapping or level, …).
    """
    data_dir = Path(data_dir)
    rows = load_perturbations(data_dir, kind)["images"][:limit]
    folder = data_dir / "perturbations" / kind
    images = []
    for r in rows:
        path = folder / r["file"]
        image = read_image(path).astype(np.float32) if kind == "objects" else np.load(path)
        images.append(resize_to_input(image, input_size))
    return np.stack(images), rows


def _tuples(scene: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in scene.items()}


def _save_input(staging: Path, name: str, image, image_id: int, seed_name: str, **fields) -> dict:
    """Write the perturbed network input ``image`` (H, W, 3), values 0–255, as
    ``staging/name``; returns its meta.json row (the seed's id and file, then ``fields``)."""
    _write_npy(staging / name, image)
    return {"image_id": image_id, "file": name, "seed_file": seed_name, **fields}


def _write_npy(path: Path, array: np.ndarray) -> None:
    import io

    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array, np.float32))
    write_bytes_atomic(path, buffer.getvalue())
