"""The 23 named airplane keypoints, defined once for the whole study.

Object frame of the airplane: x forward (towards the nose), y to the left wing, z up,
origin on the fuselage axis at mid-length, metres. The coordinates describe the default
airliner (38 m long, 36 m span, swept wings, two under-wing engines, T-less tail), all
on surfaces that an overhead camera sees. The mesh builder places its surfaces through
these points, and the COCO annotations carry the names and coordinates.
"""

from __future__ import annotations

import numpy as np

#: (name, x, y, z) in metres, in the study's keypoint order.
AIRLINER_KEYPOINTS: tuple[tuple[str, float, float, float], ...] = (
    ("nose", 18.8, 0.0, 0.2),
    ("cockpit", 16.2, 0.0, 1.6),
    ("fuselage_front", 10.0, 0.0, 2.0),
    ("fuselage_mid", 0.0, 0.0, 2.0),
    ("fuselage_rear", -10.0, 0.0, 1.9),
    ("tail_end", -19.0, 0.0, 1.1),
    ("left_wing_root_leading", 4.5, 2.0, 0.3),
    ("left_wing_root_trailing", -1.5, 2.0, 0.3),
    ("left_wing_tip_leading", -3.5, 17.9, 1.2),
    ("left_wing_tip_trailing", -5.2, 17.9, 1.2),
    ("right_wing_root_leading", 4.5, -2.0, 0.3),
    ("right_wing_root_trailing", -1.5, -2.0, 0.3),
    ("right_wing_tip_leading", -3.5, -17.9, 1.2),
    ("right_wing_tip_trailing", -5.2, -17.9, 1.2),
    ("left_engine_front", 6.5, 5.8, -0.4),
    ("right_engine_front", 6.5, -5.8, -0.4),
    ("left_stabiliser_root", -14.0, 1.0, 1.4),
    ("left_stabiliser_tip", -17.6, 6.2, 1.9),
    ("right_stabiliser_root", -14.0, -1.0, 1.4),
    ("right_stabiliser_tip", -17.6, -6.2, 1.9),
    ("fin_root", -12.8, 0.0, 2.3),
    ("fin_tip_leading", -17.8, 0.0, 8.2),
    ("fin_tip_trailing", -19.6, 0.0, 8.2),
)

KEYPOINT_NAMES: tuple[str, ...] = tuple(k[0] for k in AIRLINER_KEYPOINTS)


def airliner_keypoints() -> np.ndarray:
    """The 23 keypoints of the default airliner, shape (23, 3), metres, object frame."""
    return np.array([k[1:] for k in AIRLINER_KEYPOINTS], dtype=np.float64)
