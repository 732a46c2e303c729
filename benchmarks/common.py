"""Shared scene for the benchmarks: overhead views of the canonical 23-keypoint airliner."""

from __future__ import annotations

import copy
import json
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

from data_gen.camera import intrinsics, overhead_poses
from data_gen.keypoints import airliner_keypoints
from kpstudy.pose.geometry import project_batch
from kpstudy.verify.export import point_of_input

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


#: A verifier's counterexample may leave a float64 worst margin above 0 by this much, times
#: 1 + max |y(X0)|: the verifiers check their points in float32.
COUNTEREXAMPLE_TOLERANCE = 1e-5


def read_answer(path) -> tuple[str, np.ndarray | None]:
    """A VNN-COMP verifier's result file (NeuralSAT's ``--result_file``, α,β-CROWN's
    ``--results_file``): its answer, the first line (``sat``, ``unsat``, ``timeout``, …;
    ``''`` for an empty file), and the input of a counterexample that follows it, the
    ``(X_i value)`` pairs as an ndarray in index order (None where there are none)."""
    status, *lines = Path(path).read_text().splitlines() or [""]
    pairs = re.findall(r"\(X_(\d+)\s+([^\s)]+)\)", "\n".join(lines))
    values = {int(k): float(v) for k, v in pairs}
    return status.strip(), (np.array([values[k] for k in sorted(values)]) if values else None)


def check_counterexample(model, hull, spec, x, input_form: str = "box") -> dict:
    """The float64 re-check of a verifier's counterexample ``x`` (an assignment of an
    exported instance's ONNX input, :func:`kpstudy.verify.export.point_of_input`'s
    ``input_form``) on the torch ``model`` (the proxy) over the ``hull`` with ``spec``:
    ``inside`` (its λ lies in the hull, to 1e-6), ``margin`` (the float64 worst margin at
    its image), ``scale`` (1 + max |y(X0)|) and ``violates`` (``margin`` ≤
    :data:`COUNTEREXAMPLE_TOLERANCE` × ``scale``); a real counterexample is ``inside`` and
    ``violates``."""
    lam = point_of_input(hull, np.asarray(x)[None], input_form)
    double = copy.deepcopy(model).double()
    with torch.no_grad():
        scale = 1 + double(hull.vertices[:1].double()).abs().max().item()
        margin = spec.margins(double(hull.image(lam, dtype=torch.float64))).min().item()
    return {
        "inside": bool(hull.contains_lambda(lam, tol=1e-6).all()),
        "margin": margin,
        "scale": scale,
        "violates": margin <= COUNTEREXAMPLE_TOLERANCE * scale,
    }
