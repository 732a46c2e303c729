"""The 23 named airplane keypoints, defined once for the whole study.

Object frame of the airplane: x forward (towards the nose), y to the left wing, z up,
origin on the fuselage axis at mid-length, metres. The coordinates are those of the
default airliner mesh, ``data_gen.airplane.build_airplane('airliner')`` (38.5 m long,
35.9 m span, swept wings, two under-wing engines, low-set stabilisers), computed from
its geometry: each lies on the surface that a camera straight above sees (a test keeps
the table and the mesh equal). The COCO annotations carry the names and coordinates.
"""

from __future__ import annotations

import numpy as np

#: (name, x, y, z) in metres, in the study's keypoint order.
AIRLINER_KEYPOINTS: tuple[tuple[str, float, float, float], ...] = (
    ("nose", 18.8, 0.0, 0.190421),
    ("cockpit", 16.2, 0.0, 1.735916),
    ("fuselage_front", 10.0, 0.0, 1.98),
    ("fuselage_mid", 0.0, 0.0, 1.98),
    ("fuselage_rear", -10.0, 0.0, 1.905624),
    ("tail_end", -19.4, 0.0, 1.155556),
    ("left_wing_root_leading", 4.5, 2.0, 0.303789),
    ("left_wing_root_trailing", -1.5, 2.0, 0.218966),
    ("left_wing_tip_leading", -3.5, 17.9, 1.200583),
    ("left_wing_tip_trailing", -5.2, 17.9, 1.153052),
    ("right_wing_root_leading", 4.5, -2.0, 0.303789),
    ("right_wing_root_trailing", -1.5, -2.0, 0.218966),
    ("right_wing_tip_leading", -3.5, -17.9, 1.200583),
    ("right_wing_tip_trailing", -5.2, -17.9, 1.153052),
    ("left_engine_front", 6.5, 5.8, -0.392731),
    ("right_engine_front", 6.5, -5.8, -0.392731),
    ("left_stabiliser_root", -14.0, 1.0, 1.416027),
    ("left_stabiliser_tip", -17.6, 6.2, 1.937082),
    ("right_stabiliser_root", -14.0, -1.0, 1.416027),
    ("right_stabiliser_tip", -17.6, -6.2, 1.937082),
    ("fin_root", -12.8, 0.0, 2.317289),
    ("fin_tip_leading", -17.7, 0.0, 8.2),
    ("fin_tip_trailing", -19.3, 0.0, 8.2),
)

KEYPOINT_NAMES: tuple[str, ...] = tuple(k[0] for k in AIRLINER_KEYPOINTS)


def airliner_keypoints() -> np.ndarray:
    """The 23 keypoints of the default airliner, shape (23, 3), metres, object frame."""
    return np.array([k[1:] for k in AIRLINER_KEYPOINTS], dtype=np.float64)


#: Edges between keypoints for drawing (COCO ``skeleton``, by name).
SKELETON: tuple[tuple[str, str], ...] = (
    ("nose", "cockpit"),
    ("cockpit", "fuselage_front"),
    ("fuselage_front", "fuselage_mid"),
    ("fuselage_mid", "fuselage_rear"),
    ("fuselage_rear", "fin_root"),
    ("fin_root", "tail_end"),
    ("fin_root", "fin_tip_leading"),
    ("fin_tip_leading", "fin_tip_trailing"),
    *(
        edge
        for side in ("left", "right")
        for edge in (
            (f"{side}_wing_root_leading", f"{side}_wing_tip_leading"),
            (f"{side}_wing_tip_leading", f"{side}_wing_tip_trailing"),
            (f"{side}_wing_tip_trailing", f"{side}_wing_root_trailing"),
            (f"{side}_wing_root_trailing", f"{side}_wing_root_leading"),
            (f"{side}_wing_root_leading", "fuselage_front"),
            (f"{side}_engine_front", f"{side}_wing_root_leading"),
            (f"{side}_stabiliser_root", f"{side}_stabiliser_tip"),
            (f"{side}_stabiliser_root", "fuselage_rear"),
        )
    ),
)
