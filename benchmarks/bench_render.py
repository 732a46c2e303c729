"""Dataset rendering throughput on this machine: images per second at 640×400 and 1920×1200.

``generate_dataset`` end to end (scene draw, render, keypoint visibility, PNG encoding,
COCO), side by side with one worker process (llvmpipe then rasterises on both cores)
and with two (one OpenGL context and one rasteriser thread each); and the bare render
time of one frame (``SceneRenderer.render``), without PNG encoding and file writes.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import emit
from data_gen.airplane import build_airplane
from data_gen.camera import intrinsics
from data_gen.dataset import generate_dataset, parse_size
from data_gen.scene import SceneRenderer, sample_scene


def images_per_second(n: int, size: str, workers: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        generate_dataset(Path(tmp) / "ds", n, size, seed=0, workers=workers, progress=False)
        return n / (time.perf_counter() - start)


def render_seconds(size: str, frames: int = 10) -> float:
    width, height = parse_size(size)
    scene = SceneRenderer(build_airplane())
    K = intrinsics(width, height, 50.0)
    rng = np.random.default_rng(0)
    params = [sample_scene(scene.airplane, K, width, height, rng) for _ in range(frames)]
    scene.render(params[0], K, width, height)  # warm-up: shader compilation
    start = time.perf_counter()
    for p in params:
        scene.render(p, K, width, height)
    scene.close()
    return (time.perf_counter() - start) / frames


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--images", type=int, default=48)
    ap.add_argument("--sizes", nargs="+", default=["640x400", "1920x1200"])
    args = ap.parse_args(argv)
    result = {"images": args.images}
    for size in args.sizes:
        result[size] = {
            "images_per_s_1_worker": images_per_second(args.images, size, 1),
            "images_per_s_2_workers": images_per_second(args.images, size, 2),
            "render_only_s_per_frame": render_seconds(size),
        }
    return emit("render", result)


if __name__ == "__main__":
    main()
