"""A keypoint dataset of rendered overhead airplane images in COCO format.

``generate_dataset(out, n, …)`` writes::

    out/images/000000.png      RGB render (W×H)
    out/masks/000000.png       airplane mask (0/255)
    out/depth/000000.png       camera depth z, uint16 centimetres (DEPTH_SCALE metres per unit)
    out/annotations.json       COCO keypoints

The COCO file follows the standard keypoint layout and adds what the study needs:
the category carries the keypoint names, a skeleton and ``keypoints_3d`` (23×3,
metres, object frame); each image carries ``K`` (3×3), its ``split``
(train/val/test), ``scene`` (every drawn scene parameter) and the mask and depth
file names; each annotation carries ``keypoints`` as ``[u, v, visibility]`` triplets
in the docs/design.md pixel convention (pixel centres on integers; visibility 2 = seen,
1 = hidden behind the airplane itself), ``pose`` (``R`` 3×3, ``t`` 3, object → camera)
and the mask as run-length encoded ``segmentation``.

Image ``i`` is drawn from the seed sequence ``(seed, i)``: the bytes of an image do
not depend on the number of workers, and an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import multiprocessing
import os
import re
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from tqdm import tqdm

from data_gen.airplane import VARIANTS, Airplane, build_airplane, load_airplane
from data_gen.camera import intrinsics
from data_gen.keypoints import SKELETON
from data_gen.scene import AIRPLANE_ID, SceneRenderer, keypoint_visibility, sample_scene
from kpstudy.io import check_output_dir, staged_directory, write_bytes_atomic, write_text_atomic

DEPTH_SCALE = 0.01  # metres per unit of the depth PNGs
SPLITS = (("train", 0.8), ("val", 0.1), ("test", 0.1))
MAX_SIZE = (4096, 4096)


def parse_size(size) -> tuple[int, int]:
    """``'640x400'`` or ``(640, 400)`` → ``(width, height)``; else a ValueError naming ``size``."""
    if isinstance(size, str):
        match = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", size)
        if match is None:
            raise ValueError(f"size: expected WIDTHxHEIGHT such as 640x400, got {size!r}")
        size = (int(match[1]), int(match[2]))
    try:
        width, height = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size: expected (width, height), got {size!r}") from None
    if not (16 <= width <= MAX_SIZE[0] and 16 <= height <= MAX_SIZE[1]):
        raise ValueError(f"size: expected width and height in [16, 4096], got {width}x{height}")
    return width, height


def split_of(n: int, seed: int) -> list[str]:
    """Split name of each of ``n`` images: a seeded permutation cut 80/10/10."""
    order = np.random.default_rng([seed, 2**32 - 1]).permutation(n)
    names = np.empty(n, dtype=object)
    start = 0
    for k, (name, fraction) in enumerate(SPLITS):
        stop = n if k == len(SPLITS) - 1 else start + int(round(fraction * n))
        names[order[start:stop]] = name
        start = stop
    return list(names)


def _airplane(config: dict) -> Airplane:
    if config["mesh"] is not None:
        return load_airplane(config["mesh"], config["keypoints_json"])
    return build_airplane(config["variant"])


def render_record(
    scene: SceneRenderer, config: dict, index: int
) -> tuple[dict, dict[str, np.ndarray]]:
    """Draw and render image ``index``: its COCO image/annotation record and its pictures."""
    width, height = config["size"]
    K = intrinsics(width, height, config["hfov"])
    rng = np.random.default_rng([config["seed"], index])
    params = sample_scene(scene.airplane, K, width, height, rng)
    frame, R, t = scene.render(params, K, width, height)
    uv, visibility = keypoint_visibility(frame, scene.airplane.keypoints, R, t, K)
    mask = frame.ids == AIRPLANE_ID
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    stem = f"{index:06d}"
    record = {
        "image": {
            "id": index,
            "file_name": f"images/{stem}.png",
            "mask_file": f"masks/{stem}.png",
            "depth_file": f"depth/{stem}.png",
            "width": width,
            "height": height,
            "K": K.tolist(),
            "scene": params.as_dict(),
        },
        "annotation": {
            "id": index,
            "image_id": index,
            "category_id": 1,
            "iscrowd": 0,
            "keypoints": np.column_stack([uv, visibility]).ravel().tolist(),
            "num_keypoints": int((visibility > 0).sum()),
            "bbox": mask_utils.toBbox(rle).tolist(),
            "area": float(mask_utils.area(rle)),
            "segmentation": {"size": rle["size"], "counts": rle["counts"].decode()},
            "pose": {"R": R.tolist(), "t": t.tolist()},
        },
    }
    depth = np.clip(np.rint(frame.depth / DEPTH_SCALE), 0, 65535).astype(np.uint16)
    pictures = {"images": frame.color, "masks": mask.astype(np.uint8) * 255, "depth": depth}
    return record, pictures


_worker: dict = {}


def _init_pool_worker(config: dict, threads: int | None = None) -> None:
    # Ctrl-C reaches the whole process group: the parent alone answers it (and ends the
    # pool), the workers print no tracebacks of their own. They were born with SIGINT
    # blocked (see _sigint_held): ignore it from now on, then lift the block.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _init_worker(config, threads)


@contextlib.contextmanager
def _sigint_held():
    """Hold Ctrl-C (SIGINT) back while worker processes start.

    Processes started inside the block are born with SIGINT blocked, so a Ctrl-C while
    they import cannot print their tracebacks. Blocking it in this thread alone does not
    hold it back here: other threads (tqdm's monitor, OpenBLAS's) take it, and Python
    would raise ``KeyboardInterrupt`` in the main thread anywhere in the block (a worker
    spawned but never sent its task then prints ``EOFError``). So, on the main thread,
    a handler that only notes the signal stands in for the block's duration; a signal
    that came is delivered again when the block ends (a ``KeyboardInterrupt`` under
    Python's default handler), none is lost.
    """
    came = []
    previous_handler = None
    if threading.current_thread() is threading.main_thread():
        previous_handler = signal.getsignal(signal.SIGINT)  # None: not set from Python
        if previous_handler is not None:
            signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    try:
        if hasattr(signal, "pthread_sigmask"):  # not on Windows
            from multiprocessing import resource_tracker

            resource_tracker.ensure_running()  # started later, it would unblock SIGINT itself
            previous_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            try:
                yield
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, previous_mask)
        else:
            yield
    finally:
        if previous_handler is not None:
            # signal.signal first runs a handler still pending (ours), then restores
            signal.signal(signal.SIGINT, previous_handler)
            if came:
                signal.raise_signal(signal.SIGINT)  # to the restored handler, at once


def _init_worker(config: dict, threads: int | None = None) -> None:
    if threads is not None:  # one rasteriser thread per worker process: no oversubscription
        os.environ["LP_NUM_THREADS"] = str(threads)
    _worker["scene"] = SceneRenderer(_airplane(config), texture_seed=config["seed"])
    _worker["config"] = config


def _make(args: tuple[int, str]) -> int:
    index, staging = args
    record, pictures = render_record(_worker["scene"], _worker["config"], index)
    stem = f"{index:06d}"
    for folder, picture in pictures.items():
        write_png(Path(staging) / folder / f"{stem}.png", picture)
    # The record goes last: its presence marks image `index` as done.
    write_text_atomic(Path(staging) / "records" / f"{stem}.json", json.dumps(record))
    return index


def generate_dataset(
    out,
    n: int,
    size="640x400",
    seed: int = 0,
    variant: str = "airliner",
    *,
    workers: int = 1,
    overwrite: bool = False,
    hfov: float = 50.0,
    mesh=None,
    keypoints_json=None,
    progress: bool = True,
) -> Path:
    """Render ``n`` images of an airplane into ``out`` (see the module docstring).

    Parameters
    ----------
    out : path
        Output folder; must be empty or absent unless ``overwrite``.
    n : int
        Number of images (> 0).
    size : str or (int, int)
        Image size ``'WIDTHxHEIGHT'`` (default 640x400, the paper's 1920×1200 aspect).
    seed : int
        Seed of every random draw: same seed, same bytes.
    variant : str
        Built-in airplane (one of ``data_gen.airplane.VARIANTS``); ignored with ``mesh``.
    workers : int
        Rendering processes (each with its own OpenGL context).
    hfov : float
        Horizontal field of view of the camera, degrees.
    mesh, keypoints_json : path, optional
        A user's airplane (OBJ/GLB/PLY) and its 23 keypoints (see
        :func:`data_gen.airplane.load_airplane`), used instead of ``variant``.

    Returns
    -------
    Path of the finished dataset folder. Nothing appears at ``out`` before the end; an
    interrupted run resumes from ``.<out>.partial``.
    """
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n: expected a positive number of images, got {n}")
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise ValueError(f"workers: expected a positive integer, got {workers}")
    if mesh is None and variant not in VARIANTS:
        raise ValueError(
            f"variant: unknown airplane variant {variant!r}; expected one of {', '.join(VARIANTS)}"
        )
    if (mesh is None) != (keypoints_json is None):
        raise ValueError("mesh, keypoints_json: expected both (a user's airplane) or neither")
    if not 1.0 <= hfov <= 120.0:
        raise ValueError(f"hfov: expected a field of view in [1, 120] degrees, got {hfov}")
    seed = check_seed(seed)
    width, height = parse_size(size)
    out = check_output_dir(out, overwrite)
    config = {
        "n": int(n),
        "size": [width, height],
        "seed": int(seed),
        "variant": None if mesh is not None else variant,
        "hfov": float(hfov),
        "mesh": None if mesh is None else str(Path(mesh).resolve()),
        "keypoints_json": None if keypoints_json is None else str(Path(keypoints_json).resolve()),
    }
    airplane = _airplane(config)  # fails early on a bad user mesh, before any output

    start = time.perf_counter()
    with staged_directory(out, config) as (staging, _):
        done = {int(p.stem) for p in (staging / "records").glob("*.json")}
        todo = [(i, str(staging)) for i in range(n) if i not in done]
        bar = tqdm(total=n, initial=len(done), desc="rendering", unit="img", disable=not progress)
        with bar:  # closed (its line ended) before an error or Ctrl-C is reported
            if workers == 1 or len(todo) <= 1:
                _init_worker(config)
                for job in todo:
                    _make(job)
                    bar.update()
            else:
                context = multiprocessing.get_context("spawn")
                with contextlib.ExitStack() as stack:
                    # a Ctrl-C while the pool starts surfaces once it is whole and in
                    # `stack`, which then ends it (terminate, join) as any later one
                    with _sigint_held():
                        pool = context.Pool(workers, _init_pool_worker, (config, 1))
                        stack.enter_context(pool)
                    for _ in pool.imap_unordered(_make, todo, chunksize=4):
                        bar.update()
        records = [
            json.loads((staging / "records" / f"{i:06d}.json").read_text()) for i in range(n)
        ]
        _write_coco(staging / "annotations.json", records, airplane, config)
        for path in (staging / "records").iterdir():
            path.unlink()
        (staging / "records").rmdir()
    elapsed = time.perf_counter() - start
    rendered = len(todo)
    if progress:
        print(
            f"{rendered} images rendered in {elapsed:.1f} s "
            f"({rendered / max(elapsed, 1e-9):.2f} images/s) → {out}"
        )
    return out


def _write_coco(path: Path, records: list[dict], airplane: Airplane, config: dict) -> None:
    splits = split_of(len(records), config["seed"])
    images = [dict(r["image"], split=s) for r, s in zip(records, splits)]
    names = list(airplane.keypoint_names)
    coco = {
        "info": {
            "description": "kpstudy synthetic overhead airplane keypoints",
            "generator": "data_gen",
            "date_created": datetime.date.today().isoformat(),
            "pixel_convention": "(u, v) = (column, row), 0-based, pixel centres on integers",
            "depth_scale_m": DEPTH_SCALE,
            "config": config,
        },
        "licenses": [],
        "images": images,
        "annotations": [r["annotation"] for r in records],
        "categories": [
            {
                "id": 1,
                "name": "airplane",
                "supercategory": "aircraft",
                "airplane": airplane.name,
                "keypoints": names,
                "skeleton": [[names.index(a) + 1, names.index(b) + 1] for a, b in SKELETON],
                "keypoints_3d": airplane.keypoints.tolist(),
                "ground_z": float(airplane.ground_z),
            }
        ],
        "splits": {name: [im["id"] for im in images if im["split"] == name] for name, _ in SPLITS},
    }
    write_text_atomic(path, json.dumps(coco))


def read_image(path) -> np.ndarray:
    """An RGB image (H, W, 3) uint8 from a file; FileNotFoundError naming the path."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(f"image: cannot read {path}")
    return image[..., ::-1].copy()


def write_png(path, picture: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or single-channel (H, W) uint8/uint16 picture as PNG, atomically."""
    picture = np.asarray(picture)
    if picture.ndim == 3:
        picture = picture[..., ::-1]  # OpenCV writes BGR
    ok, png = cv2.imencode(".png", np.ascontiguousarray(picture))
    if not ok:
        raise ValueError(f"picture: cannot encode an array of shape {picture.shape} as PNG")
    write_bytes_atomic(path, png.tobytes())


def load_coco(data_dir) -> dict:
    """The dataset's COCO dictionary; FileNotFoundError naming ``data_dir`` if absent,
    ValueError naming the file if it is not a COCO dataset (not JSON, truncated, or
    without its ``images``, ``annotations`` and ``categories`` lists)."""
    path = Path(data_dir) / "annotations.json"
    if not path.is_file():
        raise FileNotFoundError(f"data_dir: no dataset at {data_dir} (expected {path})")
    coco = read_json(path, "data_dir")
    lists = ("images", "annotations", "categories")
    if not isinstance(coco, dict) or any(not isinstance(coco.get(k), list) for k in lists):
        raise ValueError(
            f"data_dir: expected a COCO dataset with {', '.join(lists)} lists in {path}"
        )
    return coco


def read_json(path, name: str):
    """The JSON document in ``path``; a ValueError naming ``name`` and the file when it is
    not JSON (corrupt, truncated) or not UTF-8."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(
            f"{name}: {path} is not valid JSON (corrupt or truncated?): {exc}"
        ) from None


def check_seed(seed, name: str = "seed") -> int:
    """``seed`` as an int; a ValueError naming ``name`` unless it is a non-negative
    integer (numpy's seed sequences take no negative entropy)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{name}: expected a non-negative integer, got {seed!r}")
    return int(seed)
