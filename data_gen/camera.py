"""Overhead camera model: intrinsics and random overhead poses of an airplane on the ground.

The airplane stands on the ground plane (object z up) with a random heading and a
random offset from the image centre; the camera looks down from an altitude in metres
(nadir, tilted by up to ``tilt_max_deg``). Poses map object to camera (OpenCV axes).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from kpstudy import _checks


def intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """Pinhole intrinsics (3, 3) with square pixels and the principal point at the centre.

    Pixel centres are on integers, so the image centre is ``((W − 1)/2, (H − 1)/2)``.
    """
    if int(width) != width or width < 1 or int(height) != height or height < 1:
        raise ValueError(f"width, height: expected positive integers, got {width}, {height}")
    if not 0 < hfov_deg < 180:
        raise ValueError(f"hfov_deg: expected a value in (0, 180), got {hfov_deg}")
    f = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def overhead_poses(
    n: int,
    seed: int,
    *,
    altitude: tuple[float, float] = (60.0, 80.0),
    tilt_max_deg: float = 20.0,
    offset_max: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Random object → camera poses of an airplane seen from above.

    Parameters
    ----------
    n : int
        Number of poses.
    seed : int
        Seed of the random draw (same seed → same poses).
    altitude : (low, high)
        Camera height above the airplane's origin, metres, uniform.
    tilt_max_deg : float
        Largest angle between the optical axis and the nadir, degrees (uniform
        direction, angle uniform in [0, tilt_max_deg]).
    offset_max : float
        Largest horizontal offset, metres, of the airplane's origin from the point where
        the optical axis meets the ground.

    Returns
    -------
    R : ndarray, shape (n, 3, 3)
    t : ndarray, shape (n, 3)
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n: expected a positive integer, got {n}")
    lo, hi = _checks.positive(altitude, "altitude", (2,))
    if lo > hi:
        raise ValueError(f"altitude: expected (low, high) with low <= high, got {altitude}")
    if not 0 <= tilt_max_deg < 90:
        raise ValueError(f"tilt_max_deg: expected a value in [0, 90), got {tilt_max_deg}")
    rng = np.random.default_rng(seed)
    heading = rng.uniform(-180.0, 180.0, n)
    h = rng.uniform(lo, hi, n)
    offset = rng.uniform(-offset_max, offset_max, (n, 2))
    tilt = np.deg2rad(tilt_max_deg) * rng.uniform(0.0, 1.0, n)
    tilt_dir = rng.uniform(0.0, 2 * np.pi, n)

    # World = object frame at heading 0 with z up; the camera first looks straight down.
    nadir = np.diag([1.0, -1.0, -1.0])
    axis = np.stack([np.cos(tilt_dir), np.sin(tilt_dir), np.zeros(n)], 1)
    R_tilt = Rotation.from_rotvec(axis * tilt[:, None]).as_matrix()
    R_world_to_cam = R_tilt @ nadir
    R_heading = Rotation.from_euler("z", heading[:, None], degrees=True).as_matrix()
    # Aim the optical axis at the point `offset` away from the airplane's origin.
    axis_world = R_world_to_cam[:, 2, :]  # optical axis in world coordinates
    aim = h[:, None] * axis_world[:, :2] / -axis_world[:, 2:3]
    cam_pos = np.concatenate([offset - aim, h[:, None]], 1)
    R = R_world_to_cam @ R_heading
    t = -np.einsum("nij,nj->ni", R_world_to_cam, cam_pos)
    return R, t
