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
from kpstudy.geometry import project_batch

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
