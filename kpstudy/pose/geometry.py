"""Camera geometry: pinhole projection, the Euler-angle convention, the pose error and
the pose tolerance box Ξ.

Conventions (docs/design.md §3): OpenCV pinhole camera (x right, y down, z forward); a pose
``(R, t)`` maps object to camera, ``x_c = R p + t``; metres and degrees; pixel
``(u, v)`` = (column, row). Euler angles are scipy's extrinsic ``'xyz'``,
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, and ``ξ = [roll, pitch, yaw, tx, ty, tz]``.

The public functions check their arguments and work in float64 numpy. The batched
kernels (``*_batch``) take numpy arrays or torch tensors with any leading batch
dimensions and do no checks; the batched PnP and the Monte Carlo study use them.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from kpstudy import _checks

#: scipy's extrinsic Euler sequence of ``ξ``'s angles: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
EULER_SEQ = "xyz"
#: The six pose axes, in the order of ``ξ`` and of every pose error.
POSE_AXES = ("roll", "pitch", "yaw", "tx", "ty", "tz")
#: The paper's tolerance scale: ``Ξ = {|δξ| ≤ α·[EPS_R, EPS_T]}`` (degrees, metres).
EPS_R = np.array([10.0, 10.0, 10.0])
#: The translation part of the tolerance scale, metres (``EPS_R``: the angles, degrees).
EPS_T = np.array([4.0, 4.0, 20.0])


def tolerance(alpha: float) -> np.ndarray:
    """Ξ's half-widths ``α·[EPS_R, EPS_T]``, shape (6,): degrees, then metres.

    >>> tolerance(1.5).tolist()
    [15.0, 15.0, 15.0, 6.0, 6.0, 30.0]
    """
    return float(alpha) * np.concatenate([EPS_R, EPS_T])


def inside_tolerance(errors, eps) -> np.ndarray:
    """Which pose errors ``(..., 6)`` (degrees, metres; numpy or torch) lie inside Ξ with
    half-widths ``eps (6,)``: every axis within (bounds included). NaN or infinite errors
    lie outside. Returns a bool array (or tensor) of shape ``(...)``.

    >>> inside_tolerance(np.array([[1.0, 0, 0, 0, 0, 0], [np.inf, 0, 0, 0, 0, 0]]),
    ...                  tolerance(1.0)).tolist()
    [True, False]
    """
    if isinstance(errors, torch.Tensor):
        return (errors <= torch.as_tensor(eps, dtype=errors.dtype)).all(-1)
    return np.all(np.asarray(errors) <= np.asarray(eps), axis=-1)


def project(P, R, t, K) -> np.ndarray:
    """Project object points into the image.

    Parameters
    ----------
    P : array_like, shape (N, 3)
        Object points in metres.
    R : array_like, shape (3, 3)
        Rotation object → camera.
    t : array_like, shape (3,)
        Translation object → camera in metres.
    K : array_like, shape (3, 3)
        Pinhole intrinsics.

    Returns
    -------
    ndarray, shape (N, 2)
        Pixel coordinates ``(u, v)``.

    Examples
    --------
    >>> project([[0, 0, 0]], np.eye(3), [0, 0, 10], [[100, 0, 32], [0, 100, 24], [0, 0, 1]])
    array([[32., 24.]])
    """
    P = _checks.float_array(P, "P", (None, 3))
    R = _checks.rotation(R)
    t = _checks.float_array(t, "t", (3,))
    K = _checks.intrinsics(K)
    depth = P @ R[2] + t[2]
    if np.any(depth <= 0):
        raise ValueError("P: expected every point in front of the camera (depth > 0)")
    return project_batch(P, R, t, K)


def project_batch(P, R, t, K):
    """Unchecked projection; shapes ``P (..., N, 3)``, ``R (..., 3, 3)``, ``t (..., 3)``,
    ``K (..., 3, 3)`` broadcast over the leading dimensions; returns ``(..., N, 2)``."""
    Xc = P @ R.swapaxes(-1, -2) + t[..., None, :]
    x = Xc @ K.swapaxes(-1, -2)
    return x[..., :2] / x[..., 2:3]


def euler_from_matrix(R) -> np.ndarray:
    """Euler angles ``[roll, pitch, yaw]`` in degrees of rotation matrices.

    Parameters
    ----------
    R : array_like, shape (3, 3) or (B, 3, 3)

    Returns
    -------
    ndarray, shape (3,) or (B, 3)
        scipy's ``Rotation.as_euler('xyz', degrees=True)``.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise ValueError(f"R: expected shape (3, 3) or (B, 3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("R: expected finite values, got NaN or inf")
    return Rotation.from_matrix(R).as_euler(EULER_SEQ, degrees=True)


def matrix_from_euler(e) -> np.ndarray:
    """Rotation matrices from Euler angles ``[roll, pitch, yaw]`` in degrees.

    Parameters
    ----------
    e : array_like, shape (3,) or (B, 3)

    Returns
    -------
    ndarray, shape (3, 3) or (B, 3, 3)
    """
    e = np.asarray(e, dtype=np.float64)
    if e.shape[-1:] != (3,) or e.ndim not in (1, 2):
        raise ValueError(f"e: expected shape (3,) or (B, 3), got {e.shape}")
    if not np.all(np.isfinite(e)):
        raise ValueError("e: expected finite values, got NaN or inf")
    return Rotation.from_euler(EULER_SEQ, e, degrees=True).as_matrix()


def matrix_from_euler_torch(e: torch.Tensor) -> torch.Tensor:
    """Differentiable ``matrix_from_euler`` for tensors ``(..., 3)`` → ``(..., 3, 3)``."""
    r, p, y = torch.deg2rad(e).unbind(-1)
    cr, sr, cp, sp, cy, sy = r.cos(), r.sin(), p.cos(), p.sin(), y.cos(), y.sin()
    rows = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def euler_from_matrix_torch(R: torch.Tensor) -> torch.Tensor:
    """``euler_from_matrix`` for tensors ``(..., 3, 3)`` → ``(..., 3)`` degrees.

    Closed form of the ``'xyz'`` convention; equals scipy's away from gimbal lock
    (``|pitch| < 90°``), which an overhead camera never approaches.
    """
    roll = torch.atan2(R[..., 2, 1], R[..., 2, 2])
    pitch = torch.asin(torch.clamp(-R[..., 2, 0], -1.0, 1.0))
    yaw = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    return torch.rad2deg(torch.stack([roll, pitch, yaw], -1))


def wrap_degrees(d):
    """Absolute angle difference wrapped into [0, 180] (numpy or torch)."""
    return abs((d + 180.0) % 360.0 - 180.0)


def pose_error(R_hat, t_hat, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis pose error of an estimate against a reference pose.

    Parameters
    ----------
    R_hat, R : array_like, shape (3, 3)
        Estimated and reference rotations.
    t_hat, t : array_like, shape (3,)
        Estimated and reference translations in metres.

    Returns
    -------
    dr : ndarray, shape (3,)
        ``|Δ[roll, pitch, yaw]|`` in degrees, wrapped into [0, 180].
    dt : ndarray, shape (3,)
        ``|Δt|`` in metres.

    Examples
    --------
    >>> dr, dt = pose_error(matrix_from_euler([179, 0, 0]), np.zeros(3),
    ...                     matrix_from_euler([-179, 0, 0]), np.zeros(3))
    >>> float(dr[0])
    2.0
    """
    e_hat = euler_from_matrix(_checks.rotation(R_hat, "R_hat"))
    e = euler_from_matrix(_checks.rotation(R, "R"))
    dt = np.abs(_checks.float_array(t_hat, "t_hat", (3,)) - _checks.float_array(t, "t", (3,)))
    return wrap_degrees(e_hat - e), dt
