"""Shared scene for the benchmarks: overhead views of the canonical 23-keypoint airliner."""

from __future__ import annotations

import json
import platform
import sys
import time

import numpy as np
import torch

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.pose.geometry import project_batch

IMAGE_SIZE = (640, 400)
HEATMAP_SCALE = (64 / 640, 64 / 400)


def scene(n: int, seed: int = 0, noise_px: float = 2.0):
    """``P (23, 3)``, ``K (3, 3)``, poses ``R (n, 3, 3)``, ``t (n, 3)``, noisy ``V (n, 23, 2)``."""
    P = airliner_keypoints()
    K = intrinsics(*IMAGE_SIZE, hfov_deg=70.0)
    R, t = overhead_poses(n, seed)
    V = project_batch(P, R, t, K) + np.random.default_rng(seed).normal(0, noise_px, (n, 23, 2))
    return P, K, R, t, V


def timed(fn, *args, repeat: int = 1, **kwargs):
    """Best wall time of ``repeat`` calls, seconds, and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - start)
    return best, out


def emit(name: str, result: dict) -> dict:
    """Print one benchmark's JSON line (with the machine it ran on) and return it."""
    result = {
        "benchmark": name,
        **result,
        "machine": {
            "python": sys.version.split()[0],
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "cpu": platform.processor() or platform.machine(),
        },
    }
    print(json.dumps(result), flush=True)
    return result


def study_hulls(data, kind: str, ms, overlapping: str, seed_index: int, level=None):
    """The level used (global kinds; ``level`` or the seed's first) and hulls of ``kind``
    from ``data``'s perturbation sets: per overlap class (``'no'``, ``'yes'``, ``'both'``)
    and ``m`` of ``ms``, the first seed image from ``seed_index`` with ``m`` such images;
    for a global kind, the first seed's hull. Each a dict of ``image_id``, ``m``,
    ``overlapping`` and the vertices ``V (n+1, H, W, 3)``."""
    from data_gen.perturb import DEFAULT_LEVELS, hull_vertices, load_perturbations

    rows = load_perturbations(data, kind)["images"]
    ids = sorted({r["image_id"] for r in rows})[seed_index:]
    if kind in DEFAULT_LEVELS:
        image_id = ids[0]
        level = level or min(r["level"] for r in rows if r["image_id"] == image_id)
        V = hull_vertices(data, image_id, kind, level=level)
        return level, [dict(image_id=image_id, m=2, overlapping=None, V=V)]
    hulls = []
    for o in {"no": [False], "yes": [True], "both": [False, True]}[overlapping]:
        count = {i: sum(r["image_id"] == i and r["overlapping"] == o for r in rows) for i in ids}
        for m in ms:
            image_id = next((i for i in ids if count[i] >= m), None)
            if image_id is not None:
                V = hull_vertices(data, image_id, kind, m, o)
                hulls.append(dict(image_id=image_id, m=m, overlapping=o, V=V))
    return None, hulls
