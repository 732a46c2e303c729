"""Occluder assets of an airport apron: ground vehicles, ground crew and equipment.

The library holds deterministic 3D meshes built from trimesh primitives at true metric
scale, meant to be rendered from above (camera 60-150 m up) and pasted over overhead
airplane images as realistic occlusions. Each asset is detailed where a top-down view
can see it: windscreens, roofs, beacons, wheels, rails, steps, hoses, vests and helmets.

Conventions of every asset:

* metres, z up; the asset stands on the ground plane (lowest vertex at z = 0);
* its x-y bounding box is centred at the origin and its length runs along x
  (vehicles and people face +x);
* every face carries an RGBA colour (``mesh.visual.face_colors``, uint8);
* no randomness: variation comes from named variants (liveries, vest colours, poses,
  body sizes), listed in ``OCCLUDER_NAMES``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import trimesh
from shapely.geometry import Polygon
from trimesh.transformations import rotation_matrix, translation_matrix

FAMILIES = ("vehicle", "person", "equipment")

Rgb = tuple[int, int, int]
Point = tuple[float, float, float]
Parts = list[trimesh.Trimesh]

# --- palette -------------------------------------------------------------------------
WHITE: Rgb = (236, 237, 233)
YELLOW: Rgb = (244, 192, 22)
ORANGE: Rgb = (238, 110, 26)
RED: Rgb = (196, 30, 36)
BLUE: Rgb = (30, 80, 165)
LIVERIES: dict[str, Rgb] = {
    "white": WHITE,
    "yellow": YELLOW,
    "orange": ORANGE,
    "red": RED,
    "blue": BLUE,
}
GLASS: Rgb = (44, 56, 70)
TYRE: Rgb = (26, 26, 28)
HUB: Rgb = (165, 165, 168)
FRAME: Rgb = (60, 60, 64)
BLACK: Rgb = (20, 20, 22)
STEEL: Rgb = (128, 131, 136)
ALUMINIUM: Rgb = (196, 199, 203)
LIGHT_GREY: Rgb = (214, 216, 218)
BEACON: Rgb = (255, 150, 0)
EMERGENCY_BLUE: Rgb = (40, 110, 255)
RAIL_YELLOW: Rgb = (250, 210, 40)
WOOD: Rgb = (180, 138, 86)
CARDBOARD: Rgb = (186, 146, 98)
DARK_GREEN: Rgb = (40, 96, 64)
PURPLE: Rgb = (112, 64, 124)
BROWN: Rgb = (124, 84, 52)
NAVY: Rgb = (32, 38, 62)
HIVIS_YELLOW: Rgb = (222, 240, 36)
HIVIS_ORANGE: Rgb = (255, 104, 22)
HIVIS_LIME: Rgb = (150, 232, 44)
REFLECTIVE: Rgb = (212, 216, 216)
WAND: Rgb = (255, 70, 30)
SKIN: tuple[Rgb, ...] = ((224, 176, 146), (176, 124, 88), (110, 74, 52))


@dataclass(frozen=True)
class Occluder:
    """One occluder asset: unique name, family and coloured mesh (conventions above)."""

    name: str
    family: str
    mesh: trimesh.Trimesh


# --- primitives ----------------------------------------------------------------------


def _paint(mesh: trimesh.Trimesh, rgb: Rgb) -> trimesh.Trimesh:
    mesh.visual.face_colors = np.array([*rgb, 255], dtype=np.uint8)
    return mesh


def _box(size: Sequence[float], center: Sequence[float], rgb: Rgb) -> trimesh.Trimesh:
    return _paint(trimesh.creation.box(extents=size, transform=translation_matrix(center)), rgb)


def _cylinder(
    radius: float,
    length: float,
    center: Sequence[float],
    rgb: Rgb,
    axis: str = "z",
    sections: int = 20,
    stretch: Sequence[float] = (1.0, 1.0, 1.0),
) -> trimesh.Trimesh:
    """Cylinder along ``axis``; ``stretch`` scales it per world axis (elliptic sections)."""
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    if axis != "z":
        mesh.apply_transform(rotation_matrix(np.pi / 2, (0, 1, 0) if axis == "x" else (1, 0, 0)))
    mesh.apply_transform(np.diag([*stretch, 1.0]))
    mesh.apply_translation(center)
    return _paint(mesh, rgb)


def _rod(start: Sequence[float], end: Sequence[float], radius: float, rgb: Rgb) -> trimesh.Trimesh:
    return _paint(trimesh.creation.cylinder(radius=radius, segment=(start, end), sections=8), rgb)


def _beam(start: Sequence[float], end: Sequence[float], size: float, rgb: Rgb) -> trimesh.Trimesh:
    """Square-section beam from ``start`` to ``end``."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    length = float(np.linalg.norm(end - start))
    mesh = trimesh.creation.box(extents=(length, size, size))
    mesh.apply_transform(trimesh.geometry.align_vectors((1.0, 0.0, 0.0), (end - start) / length))
    mesh.apply_translation((start + end) / 2)
    return _paint(mesh, rgb)


def _ball(
    radius: float, center: Sequence[float], rgb: Rgb, stretch: Sequence[float] = (1.0, 1.0, 1.0)
) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_transform(np.diag([*stretch, 1.0]))
    mesh.apply_translation(center)
    return _paint(mesh, rgb)


def _ring(major: float, minor: float, center: Sequence[float], rgb: Rgb) -> trimesh.Trimesh:
    """Flat torus (a coiled hose or cable seen from above)."""
    mesh = trimesh.creation.torus(major, minor, major_sections=28, minor_sections=8)
    mesh.apply_translation(center)
    return _paint(mesh, rgb)


# (u, v, w) of an extruded profile -> world: profile in the x-z plane, thickness along y;
# or profile in the y-z plane, thickness along x. Both are proper rotations.
_PROFILE_FRAMES = {
    "y": np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float),
    "x": np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float),
}


def _prism(
    profile: Sequence[Sequence[float]], thickness: float, rgb: Rgb, axis: str = "y", at: float = 0.0
) -> trimesh.Trimesh:
    """Side profile extruded symmetrically about ``at`` along ``axis`` ('y': profile in x-z)."""
    mesh = trimesh.creation.extrude_polygon(Polygon(profile), thickness)
    mesh.apply_translation((0.0, 0.0, -thickness / 2))
    mesh.apply_transform(_PROFILE_FRAMES[axis])
    mesh.apply_translation((at, 0.0, 0.0) if axis == "x" else (0.0, at, 0.0))
    return _paint(mesh, rgb)


def _assemble(parts: Parts) -> trimesh.Trimesh:
    """Concatenate coloured parts; put the result on z = 0 and centre it in x-y."""
    mesh = trimesh.util.concatenate(parts)
    lo, hi = mesh.bounds
    mesh.apply_translation((-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]))
    return mesh


# --- vehicle parts -------------------------------------------------------------------


def _wheels(xs: Sequence[float], track: float, radius: float, width: float) -> Parts:
    """Tyres with hub caps; ``track`` is between tyre centres."""
    parts = []
    for x in xs:
        for y in (track / 2, -track / 2):
            parts.append(_cylinder(radius, width, (x, y, radius), TYRE, axis="y", sections=18))
            parts.append(_cylinder(0.55 * radius, width + 0.02, (x, y, radius), HUB, axis="y"))
    return parts


def _beacon(x: float, y: float, z: float, rgb: Rgb = BEACON) -> Parts:
    return [
        _cylinder(0.11, 0.05, (x, y, z + 0.025), BLACK, sections=12),
        _cylinder(0.08, 0.16, (x, y, z + 0.13), rgb, sections=12),
    ]


def _light_bar(x: float, z: float, width: float, rgb: Rgb = BEACON) -> Parts:
    return [
        _box((0.3, width, 0.06), (x, 0.0, z + 0.03), BLACK),
        _box((0.22, width - 0.1, 0.1), (x, 0.0, z + 0.1), rgb),
    ]


def _railing(
    start: Point, end: Point, height: float, rgb: Rgb = RAIL_YELLOW, posts: int = 3
) -> Parts:
    """Hand rail ``height`` above the line start-end, on ``posts`` evenly spaced posts."""
    start_, end_ = np.asarray(start, float), np.asarray(end, float)
    up = np.array([0.0, 0.0, height])
    parts = [_rod(start_ + up, end_ + up, 0.03, rgb)]
    for t in np.linspace(0.0, 1.0, posts):
        foot = start_ + t * (end_ - start_)
        parts.append(_rod(foot, foot + up, 0.025, rgb))
    return parts


def _scissor(x0: float, x1: float, y: float, z0: float, z1: float) -> Parts:
    """One side of a scissor lift between heights z0 and z1."""
    return [
        _beam((x0, y, z0), (x1, y, z1), 0.12, STEEL),
        _beam((x1, y, z0), (x0, y, z1), 0.12, STEEL),
    ]


def _cab(
    front: float,
    back: float,
    floor: float,
    top: float,
    width: float,
    rgb: Rgb,
    sill: float | None = None,
    rake: float = 0.55,
) -> Parts:
    """Driver's cab: body with a raked windscreen (seen from above as a dark band) and side
    windows. ``sill`` is where the windscreen starts (default half-way up), ``rake`` how far
    back it leans."""
    sill = (floor + top) / 2 if sill is None else sill
    profile = [(back, floor), (front, floor)]
    profile += [(front, sill)] if sill > floor + 1e-6 else []
    profile += [(front - rake, top), (back, top)]
    parts = [_prism(profile, width, rgb)]
    lower, upper = np.array([front, sill]), np.array([front - rake, top])
    along = upper - lower
    normal = np.array([along[1], -along[0]]) / np.linalg.norm(along)
    a, b = lower + 0.06 * along, upper - 0.08 * along
    parts.append(_prism([a, b, b + 0.03 * normal, a + 0.03 * normal], 0.9 * width, GLASS))
    window_len = front - rake - back - 0.3
    if window_len > 0.2:
        for y in (width / 2, -width / 2):
            parts.append(
                _box(
                    (window_len, 0.03, 0.7 * (top - sill)),
                    (back + 0.15 + window_len / 2, y, (sill + top) / 2 + 0.05),
                    GLASS,
                )
            )
    return parts


def _glasshouse(
    foot_front: float,
    roof_front: float,
    roof_back: float,
    foot_back: float,
    base: float,
    roof: float,
    width: float,
    rgb: Rgb,
) -> Parts:
    """Car cabin: glass all round (windscreen, side and rear windows) under a painted roof."""
    glass = [(foot_front, base), (roof_front, roof), (roof_back, roof), (foot_back, base)]
    roof_len = roof_front - roof_back - 0.1
    return [
        _prism(glass, width, GLASS),
        _box((roof_len, width - 0.08, 0.06), ((roof_front + roof_back) / 2, 0, roof), rgb),
    ]


def _mirrors_and_lamps(front: float, rear: float, width: float, z: float, mirror_x: float) -> Parts:
    """Side mirrors, headlamps and tail lamps of a road vehicle."""
    parts = []
    for side in (1, -1):
        parts.append(_box((0.08, 0.2, 0.14), (mirror_x, side * (width / 2 + 0.1), z + 0.3), BLACK))
        parts.append(_box((0.05, 0.28, 0.12), (front, side * (width / 2 - 0.22), z), LIGHT_GREY))
        parts.append(_box((0.05, 0.2, 0.15), (rear, side * (width / 2 - 0.16), z), RED))
    return parts


def _truck(
    livery: Rgb,
    length: float,
    axles: Sequence[float],
    width: float = 2.5,
    cab_len: float = 2.1,
    cab_height: float = 2.3,
    wheel_radius: float = 0.5,
) -> tuple[Parts, float, float]:
    """Rigid truck facing +x: wheels, ladder frame, bumper and cab with a roof beacon.

    Returns the parts, the height of the frame top (where bodies sit) and the x where the
    free frame behind the cab ends."""
    front = length / 2
    floor = wheel_radius + 0.1
    wheel_w = 0.4
    parts = _wheels(axles, width - wheel_w + 0.06, wheel_radius, wheel_w)
    parts.append(_box((length - 0.2, 1.0, 0.3), (-0.1, 0.0, floor - 0.1), FRAME))
    parts.append(_box((0.2, width, 0.35), (front - 0.05, 0.0, floor - 0.15), BLACK))
    back = front - cab_len
    parts += _cab(front - 0.05, back, floor, floor + cab_height, width, livery)
    parts += _beacon(back + 0.4, 0.0, floor + cab_height)
    return parts, floor + 0.05, back - 0.1


def _tank(
    x0: float, x1: float, half_width: float, half_height: float, base: float, rgb: Rgb, trim: Rgb
) -> Parts:
    """Horizontal tank with domed ends, a top walkway with manholes, hand rails and a stripe."""
    mid, zc, top = (x0 + x1) / 2, base + half_height, base + 2 * half_height
    parts = [
        _cylinder(1.0, x1 - x0, (mid, 0, zc), rgb, "x", 28, (1.0, half_width, half_height)),
        _box((x1 - x0 - 0.6, 1.0, half_height), (mid, 0, base + half_height / 2), FRAME),
        _box((x1 - x0 - 0.5, 0.55, 0.05), (mid, 0, top + 0.02), STEEL),
    ]
    for x in (x0, x1):
        parts.append(_ball(1.0, (x, 0, zc), rgb, (0.25, half_width, half_height)))
    for x in np.linspace(x0 + 0.9, x1 - 0.9, 3):
        parts.append(_cylinder(0.22, 0.1, (x, 0, top + 0.06), LIGHT_GREY))
    for y in (0.33, -0.33):
        parts += _railing((x0 + 0.4, y, top), (x1 - 0.4, y, top), 0.45, RAIL_YELLOW, 4)
    for y in (half_width, -half_width):
        parts.append(_box((x1 - x0, 0.04, 0.25), (mid, y, zc), trim))
    return parts


def _generator(x: float, z: float, length: float, width: float, height: float, rgb: Rgb) -> Parts:
    """Engine-generator housing (GPU / air start unit): vent grilles and exhaust on the roof."""
    top = z + height
    parts = [_box((length, width, height), (x, 0, z + height / 2), rgb)]
    for k in range(4):
        parts.append(_box((0.08, width * 0.6, 0.02), (x - length * 0.35 + 0.16 * k, 0, top), BLACK))
    parts.append(_cylinder(0.06, 0.3, (x + length * 0.3, width * 0.3, top + 0.15), STEEL))
    parts.append(
        _box((0.03, width * 0.5, height * 0.4), (x + length / 2, 0, z + height * 0.6), FRAME)
    )
    return parts


# --- vehicles ------------------------------------------------------------------------


def _baggage_tractor(livery: Rgb) -> Parts:
    parts = _wheels((0.95, -0.95), 1.32, 0.33, 0.24)
    parts += [
        _box((3.0, 1.4, 0.55), (0.0, 0.0, 0.58), livery),  # chassis
        _box((1.0, 1.3, 0.3), (1.0, 0.0, 1.0), livery),  # bonnet
        _box((0.05, 1.0, 0.3), (1.52, 0.0, 0.95), FRAME),  # grille
        _box((0.5, 0.9, 0.4), (-0.55, 0.0, 1.05), BLACK),  # seat
        _box((0.3, 0.5, 0.15), (-1.58, 0.0, 0.5), FRAME),  # tow hitch
        _box((1.5, 1.46, 0.06), (-0.65, 0.0, 2.0), livery),  # canopy roof
    ]
    for y in (0.3, 0.0, -0.3):  # bonnet vents
        parts.append(_box((0.6, 0.12, 0.02), (1.0, y, 1.16), FRAME))
    for x in (-1.35, 0.45):
        for y in (0.66, -0.66):
            parts.append(_rod((x, y, 0.85), (x, y, 1.98), 0.03, FRAME))
    parts.append(_prism([(0.5, 1.15), (0.56, 1.15), (0.12, 1.98), (0.06, 1.98)], 1.3, GLASS))
    parts += _beacon(-0.65, 0.0, 2.03)
    return parts


def _fuel_truck(livery: Rgb) -> Parts:
    parts, deck, body_front = _truck(
        livery, 10.0, (3.4, -2.2, -3.5), cab_height=2.4, wheel_radius=0.52
    )
    parts += _tank(
        -4.7, body_front - 0.45, 1.18, 0.98, deck, livery, RED if livery != RED else WHITE
    )
    parts.append(_box((0.5, 2.3, 1.6), (-4.75, 0.0, deck + 0.8), STEEL))  # rear hose cabinet
    parts.append(_ring(0.35, 0.06, (-4.75, 0.0, deck + 1.66), BLACK))
    return parts


def _catering_truck(livery: Rgb) -> Parts:
    parts, deck, body_front = _truck(livery, 9.0, (3.0, -2.6), cab_len=2.0)
    rear, lift, body_top = -4.5, 3.2, 5.6
    body_end = body_front - 0.2
    parts.append(_box((body_front - rear, 2.3, 0.15), ((rear + body_front) / 2, 0, deck), STEEL))
    for y in (1.0, -1.0):
        parts += _scissor(rear + 0.4, body_end - 0.4, y, deck, lift)
    parts += [
        _box(
            (body_end - rear, 2.5, body_top - lift),
            ((rear + body_end) / 2, 0, (lift + body_top) / 2),
            livery,
        ),
        _box(
            (body_end - rear, 2.52, 0.3),
            ((rear + body_end) / 2, 0, lift + 0.5),
            BLUE if livery != BLUE else WHITE,
        ),  # livery stripe
        _box((0.8, 1.7, 0.35), (body_end - 0.6, 0, body_top + 0.17), LIGHT_GREY),  # fridge unit
        _box((0.5, 1.3, 0.02), (body_end - 0.6, 0, body_top + 0.35), BLACK),
        _box((4.5 - body_end, 2.3, 0.12), ((4.5 + body_end) / 2, 0, lift), STEEL),  # platform
    ]
    for y in (1.12, -1.12):
        parts += _railing((body_end, y, lift), (4.45, y, lift), 1.0)
    parts += _railing((4.45, 1.12, lift), (4.45, -1.12, lift), 1.0, posts=2)
    return parts


def _pushback_tug(livery: Rgb) -> Parts:
    parts = _wheels((1.95, -1.95), 2.4, 0.6, 0.5)
    body = [
        (-2.8, 0.3),
        (2.8, 0.3),
        (3.0, 0.55),
        (3.0, 0.95),
        (2.6, 1.25),
        (-2.6, 1.25),
        (-3.0, 0.95),
        (-3.0, 0.55),
    ]
    parts.append(_prism(body, 2.9, livery))
    for x in (3.05, -3.05):
        parts.append(_box((0.15, 2.5, 0.3), (x, 0.0, 0.6), BLACK))  # bumpers
        parts.append(_box((0.4, 0.3, 0.2), (x * 1.04, 0.0, 0.5), FRAME))  # tow hitch
    for k in range(6):  # black and yellow hazard chevrons on the front deck edge
        parts.append(
            _box((0.3, 0.36, 0.02), (2.55, -1.05 + 0.42 * k, 1.26), (BLACK, YELLOW)[k % 2])
        )
    parts += [
        _prism(
            [(-1.4, 1.25), (0.8, 1.25), (0.45, 1.95), (-1.1, 1.95)], 0.82, GLASS, at=0.85
        ),  # cab
        _box((1.45, 0.9, 0.08), (-0.32, 0.85, 1.98), livery),
        _box((2.2, 1.6, 0.04), (-0.2, -0.45, 1.27), STEEL),  # ballast deck plate
    ]
    parts += _beacon(-0.9, 0.85, 2.02)
    return parts


def _belt_loader(livery: Rgb) -> Parts:
    parts = _wheels((2.2, -2.0), 1.95, 0.33, 0.25)
    parts.append(_box((6.4, 2.0, 0.5), (-0.1, 0.0, 0.55), livery))
    x0, z0, x1, z1 = -3.7, 1.0, 3.75, 3.1
    slope = (z1 - z0) / (x1 - x0)
    y_belt = -0.45
    parts.append(
        _prism([(x0, z0), (x1, z1), (x1, z1 - 0.3), (x0, z0 - 0.3)], 1.0, livery, at=y_belt)
    )
    parts.append(
        _prism(
            [(x0, z0 + 0.02), (x1, z1 + 0.02), (x1, z1 - 0.02), (x0, z0 - 0.02)],
            0.8,
            BLACK,
            at=y_belt,
        )
    )
    for x in np.arange(x0 + 0.25, x1, 0.45):  # cleats on the belt
        parts.append(_box((0.06, 0.76, 0.04), (x, y_belt, z0 + slope * (x - x0) + 0.04), STEEL))
    for y in (y_belt + 0.5, y_belt - 0.5):
        parts += _railing(
            (x0 + 0.3, y, z0 + slope * 0.3), (x1 - 0.1, y, z1 - slope * 0.1), 0.3, livery, 4
        )
    parts.append(
        _beam((-1.5, y_belt, 0.8), (1.2, y_belt, z0 + slope * (1.2 - x0) - 0.3), 0.14, FRAME)
    )
    parts.append(_box((0.25, 1.0, 0.25), (x1 + 0.05, y_belt, z1 - 0.1), BLACK))  # bumper pad
    parts += [
        _box((1.2, 0.7, 0.4), (-1.9, 0.6, 1.0), BLACK),  # driver seat
        _box((1.4, 0.8, 0.06), (-1.9, 0.6, 2.05), livery),  # canopy
    ]
    for x in (-2.5, -1.3):
        parts.append(_rod((x, 0.95, 0.8), (x, 0.95, 2.03), 0.03, FRAME))
    parts += _beacon(-2.3, 0.6, 2.08)
    return parts


def _stairs_truck(livery: Rgb) -> Parts:
    parts, deck, _ = _truck(livery, 8.5, (2.9, -2.4), cab_len=1.9, cab_height=2.0)
    parts.append(_box((6.3, 2.4, 0.6), (-1.0, 0.0, deck + 0.3), livery))  # lockers
    base, top, run, rise = deck + 0.6, 3.7, 0.4, 0.2
    steps = round((top - base) / rise)
    x_start = 1.8 - steps * run
    for k in range(steps):
        x, z = x_start + k * run, base + (k + 1) * rise
        parts.append(_box((run, 1.4, 0.05), (x + run / 2, 0, z - 0.025), STEEL))
        parts.append(_box((0.07, 1.4, 0.06), (x + 0.035, 0, z), RAIL_YELLOW))  # step nosing
    for y in (0.74, -0.74):
        parts.append(
            _prism(
                [(x_start, base), (1.8, top), (1.8, top - 0.35), (x_start, base - 0.35)],
                0.08,
                livery,
                at=y,
            )
        )
        parts += _railing((x_start, y, base), (1.8, y, top), 1.0, WHITE, 5)
        parts += _railing((1.8, y, top), (4.0, y, top), 1.0, WHITE, 2)
    parts.append(_box((2.2, 1.6, 0.1), (2.9, 0.0, top - 0.05), STEEL))  # top platform
    parts.append(_box((0.15, 1.6, 0.25), (4.05, 0.0, top - 0.05), BLACK))  # rubber bumper
    for x in (1.2, 3.6):
        parts.append(_rod((x, 0.5, deck + 0.6), (x, 0.5, top - 0.1), 0.06, FRAME))
    return parts


def _apron_bus(livery: Rgb) -> Parts:
    half = 6.75
    outline = Polygon([(-half, -1.5), (half, -1.5), (half, 1.5), (-half, 1.5)])
    lower = trimesh.creation.extrude_polygon(outline.buffer(-0.3).buffer(0.3), 0.85)
    lower.apply_translation((0, 0, 0.35))
    parts = _wheels((4.5, -4.3), 2.62, 0.45, 0.36)
    parts.append(_paint(lower, livery))
    greenhouse = [
        (-half + 0.05, 1.18),
        (half, 1.18),
        (half, 1.4),
        (half - 0.4, 2.75),
        (-half + 0.2, 2.75),
        (-half + 0.05, 2.4),
    ]
    parts.append(_prism(greenhouse, 2.94, GLASS))
    parts.append(_box((12.6, 2.8, 0.14), (-0.25, 0, 2.78), livery))  # roof
    for x in (3.0, -3.6):  # air-conditioning units with fan discs
        parts.append(_box((2.0, 1.7, 0.26), (x, 0, 2.98), LIGHT_GREY))
        for dx in (0.5, -0.5):
            parts.append(_cylinder(0.3, 0.04, (x + dx, 0, 3.12), FRAME))
    for x in (0.0, 5.2):
        parts.append(_box((0.7, 0.7, 0.06), (x, 0, 2.87), STEEL))  # roof hatches
    return parts


def _bonnet(
    front: float,
    rear: float,
    ground: float,
    bumper: float,
    screen_x: float,
    screen_z: float,
    tail: float,
    step_x: float | None = None,
) -> list[tuple[float, float]]:
    """Side profile (x, z) of a road vehicle's lower body: bumper, bonnet rising to the
    windscreen foot (screen_x, screen_z), then back to the rear at height ``tail`` (dropping
    at ``step_x`` first for a pickup bed)."""
    profile = [(rear, ground), (front, ground), (front, bumper)]
    profile += [(front - 0.17, screen_z - 0.11), (screen_x, screen_z)]
    if step_x is not None:
        profile.append((step_x, screen_z))
        profile.append((step_x, tail))
    return profile + [(rear, tail)]


def _car(livery: Rgb, roof: str) -> Parts:
    """Saloon / estate car; ``roof``: 'light_bar' (ops car) or 'checker' (follow-me car)."""
    front, rear, width = 2.25, -2.25, 1.8
    parts = _wheels((1.4, -1.35), width - 0.18, 0.32, 0.22)
    parts.append(_prism(_bonnet(front, rear, 0.22, 0.62, front - 1.1, 0.93, 0.9), width, livery))
    parts += _glasshouse(front - 1.1, 0.3, -1.35, rear + 0.3, 0.9, 1.48, width - 0.16, livery)
    parts += _mirrors_and_lamps(front, rear, width, 0.7, front - 1.2)
    if roof == "checker":
        for i in range(5):
            for j in range(3):
                if (i + j) % 2 == 0:
                    parts.append(
                        _box((0.3, 0.5, 0.02), (0.0 - 0.3 * i, -0.5 + 0.5 * j, 1.52), BLACK)
                    )
        parts.append(_box((0.08, 1.2, 0.4), (0.05, 0.0, 1.71), YELLOW))  # FOLLOW ME board
        parts.append(_box((0.1, 1.22, 0.06), (0.05, 0.0, 1.94), BEACON))
    else:
        parts += _light_bar(-0.4, 1.51, 1.2)
        for side in (1, -1):
            parts.append(_box((4.2, 0.03, 0.15), (0, side * width / 2, 0.55), ORANGE))
    return parts


def _pickup(livery: Rgb) -> Parts:
    front, rear, width = 2.65, -2.65, 1.9
    lower = _bonnet(front, rear, 0.35, 0.78, 1.5, 1.08, 0.72, step_x=-0.45)
    parts = _wheels((1.65, -1.6), width - 0.18, 0.38, 0.26)
    parts.append(_prism(lower, width, livery))
    parts += _glasshouse(1.5, 0.75, -0.35, -0.45, 1.05, 1.8, width - 0.12, livery)
    parts += [
        _box((2.15, width - 0.16, 0.04), (-1.55, 0, 0.74), FRAME),  # bed floor
        _box((0.08, width, 0.45), (rear + 0.04, 0, 0.95), livery),  # tailgate
        _box((0.5, 1.2, 0.35), (-0.8, 0, 0.93), STEEL),  # tool box
    ]
    for side in (1, -1):
        parts.append(_box((2.2, 0.08, 0.45), (-1.55, side * (width / 2 - 0.04), 0.95), livery))
    parts += _mirrors_and_lamps(front, rear, width, 0.8, 1.4)
    parts += _light_bar(0.2, 1.83, 1.3)
    return parts


def _van_front(front: float, width: float, livery: Rgb) -> Parts:
    """Short bonnet of a van or ambulance, from the nose back to x = front - 0.6."""
    return [_prism(_bonnet(front, front - 0.7, 0.35, 0.8, front - 0.6, 1.1, 1.1), width, livery)]


def _van(livery: Rgb) -> Parts:
    front, rear, width = 2.5, -2.5, 2.0
    parts = _wheels((1.7, -1.7), width - 0.2, 0.36, 0.24)
    parts += _van_front(front, width, livery)
    parts += _cab(front - 0.6, rear, 0.35, 2.35, width, livery, sill=1.1, rake=0.7)
    parts += _mirrors_and_lamps(front, rear, width, 0.8, front - 0.8)
    for x in (-0.5, -1.8):  # roof rack bars
        parts.append(_box((0.06, width - 0.2, 0.06), (x, 0, 2.4), STEEL))
    parts += _beacon(0.8, 0.0, 2.35)
    for side in (1, -1):
        parts.append(_box((4.6, 0.03, 0.18), (-0.1, side * width / 2, 0.7), ORANGE))
    return parts


def _ambulance(livery: Rgb) -> Parts:
    front, rear, width = 3.1, -3.1, 2.2
    parts = _wheels((2.3, -1.9), width - 0.2, 0.38, 0.26)
    parts += _van_front(front, width - 0.1, livery)
    parts += _cab(front - 0.6, front - 2.0, 0.35, 2.3, width - 0.1, livery, sill=1.1, rake=0.7)
    parts.append(_box((4.3, width, 2.3), (rear + 2.15, 0, 0.35 + 1.15), livery))  # patient box
    for size in ((1.1, 0.35, 0.02), (0.35, 1.1, 0.02)):  # red cross on the roof
        parts.append(_box(size, (rear + 2.15, 0, 2.66), RED))
    for side in (1, -1):
        parts.append(_box((6.0, 0.03, 0.25), (0, side * (width / 2 + 0.01), 1.1), RED))
        parts += _beacon(rear + 0.3, side * 0.85, 2.65, EMERGENCY_BLUE)
    parts += _light_bar(front - 1.7, 2.3, 1.6, EMERGENCY_BLUE)
    parts += _mirrors_and_lamps(front, rear, width, 0.8, front - 0.8)
    return parts


def _deicing_truck(livery: Rgb) -> Parts:
    parts, deck, body_front = _truck(livery, 9.5, (3.2, -2.4), cab_height=2.3)
    rear = -4.75
    parts.append(
        _box((body_front - rear, 2.45, 1.8), ((rear + body_front) / 2, 0, deck + 0.9), livery)
    )
    parts.append(
        _box((body_front - rear - 0.4, 1.6, 0.05), ((rear + body_front) / 2, 0, deck + 1.82), STEEL)
    )
    turret = (-3.8, 0.0, deck + 2.1)
    tip = (2.6, 0.0, 4.9)
    parts += [
        _cylinder(0.5, 0.3, (-3.8, 0.0, deck + 1.95), FRAME),
        _beam(turret, tip, 0.35, livery),
        _rod((turret[0], 0.25, turret[2] + 0.2), (tip[0], 0.25, tip[2] + 0.2), 0.05, BLACK),  # hose
        _box((1.3, 1.3, 1.3), (3.3, 0.0, 5.0), GLASS),  # operator basket
        _box((1.4, 1.4, 0.08), (3.3, 0.0, 5.68), WHITE if livery != WHITE else ORANGE),
        _rod((3.95, 0.35, 4.6), (4.45, 0.35, 4.4), 0.05, STEEL),  # spray nozzle
    ]
    parts += _beacon(3.3, 0.0, 5.72)
    return parts


def _service_truck(livery: Rgb, tank: str, trim: Rgb) -> Parts:
    """Lavatory ('cylinder' tank) or potable-water ('box' tank) truck with a rear platform."""
    parts, deck, body_front = _truck(
        livery, 6.8, (2.2, -1.8), width=2.3, cab_len=2.0, cab_height=2.2, wheel_radius=0.45
    )
    tank_rear = -2.0
    if tank == "cylinder":
        parts += _tank(tank_rear + 0.2, body_front - 0.2, 0.9, 0.7, deck, STEEL, trim)
    else:
        mid = (tank_rear + body_front) / 2
        parts.append(_box((body_front - tank_rear, 2.2, 1.6), (mid, 0, deck + 0.8), WHITE))
        parts.append(_box((body_front - tank_rear, 2.22, 0.3), (mid, 0, deck + 0.9), trim))
        parts.append(_cylinder(0.25, 0.1, (mid, 0.0, deck + 1.65), LIGHT_GREY))
    lift = 2.0
    for y in (0.8, -0.8):
        parts += _scissor(-3.3, -2.2, y, deck, lift)
    parts.append(_box((1.3, 2.0, 0.1), (-2.75, 0.0, lift), STEEL))
    parts += _railing((-3.4, 0.95, lift), (-3.4, -0.95, lift), 1.0, posts=2)
    for y in (0.95, -0.95):
        parts += _railing((-3.4, y, lift), (-2.1, y, lift), 1.0, posts=2)
    parts.append(_ring(0.3, 0.05, (-2.75, 0.0, lift + 0.1), BLACK))  # hose coil
    return parts


def _gpu_truck(livery: Rgb) -> Parts:
    parts, deck, body_front = _truck(
        livery, 5.6, (1.8, -1.6), width=2.2, cab_len=1.9, cab_height=2.1, wheel_radius=0.42
    )
    parts.append(_box((body_front + 2.8, 2.2, 0.1), ((body_front - 2.8) / 2, 0, deck), STEEL))
    parts += _generator(-0.9, deck + 0.05, 2.6, 1.8, 1.2, livery)
    parts.append(_cylinder(0.45, 0.6, (-2.45, 0.0, deck + 0.5), BLACK, axis="y"))  # cable drum
    return parts


def _fire_truck(livery: Rgb) -> Parts:
    parts, deck, body_front = _truck(
        livery, 11.0, (4.0, -1.8, -3.6), width=3.0, cab_len=2.5, cab_height=2.6, wheel_radius=0.65
    )
    rear, top = -5.5, deck + 2.5
    mid = (rear + body_front) / 2
    parts.append(_box((body_front - rear, 3.0, 2.5), (mid, 0, deck + 1.25), livery))
    parts.append(_box((body_front - rear - 0.6, 1.6, 0.04), (mid, -0.2, top), STEEL))  # walkway
    for side in (1, -1):
        parts.append(_box((11.0, 0.03, 0.2), (0.0, side * 1.52, deck + 0.6), WHITE))
        parts.append(
            _rod(
                (rear + 0.3, side * 1.2, top + 0.25),
                (body_front - 0.3, side * 1.2, top + 0.25),
                0.04,
                ALUMINIUM,
            )
        )  # roof ladder rails
    for x in np.arange(rear + 0.5, body_front - 0.3, 0.35):
        parts.append(_rod((x, 0.95, top + 0.25), (x, 1.45, top + 0.25), 0.02, ALUMINIUM))
    cab_top = 0.75 + 2.6
    parts += [
        _cylinder(0.35, 0.3, (4.0, 0.0, cab_top + 0.15), STEEL),  # roof turret
        _rod((4.0, 0.0, cab_top + 0.45), (5.3, 0.0, cab_top + 0.55), 0.09, STEEL),
    ]
    parts += _light_bar(5.0, cab_top - 0.25, 2.2, RED)
    return parts


def _forklift(livery: Rgb) -> Parts:
    parts = _wheels((0.35,), 1.0, 0.33, 0.25) + _wheels((-1.15,), 0.9, 0.26, 0.2)
    parts += [
        _box((2.0, 1.1, 0.6), (-0.45, 0.0, 0.6), livery),  # chassis
        _box((0.5, 1.12, 0.75), (-1.25, 0.0, 0.9), FRAME),  # counterweight
        _box((0.5, 0.6, 0.5), (-0.55, 0.0, 1.15), BLACK),  # seat
        _box((1.4, 1.0, 0.06), (-0.35, 0.0, 2.15), livery),  # overhead guard
    ]
    for k in range(4):
        parts.append(_box((1.3, 0.04, 0.04), (-0.35, -0.3 + 0.2 * k, 2.2), BLACK))
    for x in (-1.0, 0.3):
        for y in (0.47, -0.47):
            parts.append(_rod((x, y, 0.9), (x, y, 2.14), 0.035, livery))
    for y in (0.38, -0.38):
        parts.append(_box((0.1, 0.1, 2.3), (0.75, y, 1.2), FRAME))  # mast
        parts.append(_box((1.2, 0.12, 0.05), (1.45, y * 0.8, 0.12), STEEL))  # forks
    parts.append(_box((0.06, 0.95, 0.5), (0.85, 0.0, 0.45), STEEL))  # fork carriage
    parts += _beacon(-0.8, 0.0, 2.18)
    return parts


def _rollers(x0: float, x1: float, width: float, z: float, pitch: float = 0.25) -> Parts:
    """Roller bed of a ULD dolly or loader platform."""
    return [
        _cylinder(0.04, width, (x, 0.0, z), ALUMINIUM, axis="y", sections=8)
        for x in np.arange(x0 + pitch / 2, x1, pitch)
    ]


def _container_loader(livery: Rgb) -> Parts:
    parts = _wheels((3.1, -3.1), 3.0, 0.35, 0.3)
    parts.append(_box((8.0, 3.0, 0.45), (0.0, 0.0, 0.6), livery))  # chassis
    main, bridge = 1.8, 2.7
    for y in (1.1, -1.1):
        parts += _scissor(-3.7, 0.0, y, 0.85, main)
    parts.append(_box((4.6, 3.5, 0.2), (-1.9, 0.0, main - 0.1), livery))
    parts += _rollers(-4.1, 0.3, 3.0, main + 0.02)
    for y in (1.7, -1.7):
        parts += _railing((-4.1, y, main), (0.3, y, main), 0.3, RAIL_YELLOW, 4)
    for x in (1.0, 3.6):
        parts.append(_rod((x, 0.0, 0.85), (x, 0.0, bridge - 0.1), 0.1, FRAME))
    parts.append(_box((3.8, 2.8, 0.2), (2.4, 0.0, bridge - 0.1), livery))
    parts += _rollers(0.6, 4.2, 1.7, bridge + 0.02)
    parts.append(_box((0.25, 2.6, 0.25), (4.35, 0.0, bridge - 0.1), BLACK))  # bumper pad
    parts += [
        _box((1.1, 0.9, 1.3), (2.4, 1.0, bridge + 0.65), GLASS),  # operator station
        _box((1.2, 1.0, 0.08), (2.4, 1.0, bridge + 1.34), livery),
    ]
    parts += _beacon(2.1, 1.0, bridge + 1.38)
    return parts


# --- people --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Pose:
    """Joints of a 1.75 m reference body (x forward, y left, z up), (left, right) pairs.

    Elbows and hands are in the upper-body frame (hips at height 0.92, upright); the upper
    body is then bent forward by ``lean`` degrees about the hips placed at ``pelvis``."""

    elbows: tuple[Point, Point]
    hands: tuple[Point, Point]
    knees: tuple[Point, Point] = ((0.02, 0.1, 0.5), (0.02, -0.1, 0.5))
    ankles: tuple[Point, Point] = ((0.0, 0.1, 0.09), (0.0, -0.1, 0.09))
    pelvis: tuple[float, float] = (0.0, 0.92)
    lean: float = 0.0
    held: str = ""  # "wands" or "box"


def _pair(left: Point) -> tuple[Point, Point]:
    return left, (left[0], -left[1], left[2])


_POSES: dict[str, _Pose] = {
    "standing": _Pose(_pair((-0.03, 0.25, 1.13)), _pair((0.0, 0.26, 0.87))),
    "walking": _Pose(
        elbows=((-0.13, 0.24, 1.15), (0.1, -0.24, 1.15)),
        hands=((-0.24, 0.25, 0.92), (0.28, -0.24, 0.96)),
        knees=((0.2, 0.1, 0.5), (-0.1, -0.1, 0.5)),
        ankles=((0.33, 0.1, 0.09), (-0.34, -0.1, 0.13)),
        pelvis=(0.0, 0.89),
    ),
    "wands_up": _Pose(_pair((0.02, 0.47, 1.36)), _pair((0.1, 0.48, 1.62)), held="wands"),
    "wands_forward": _Pose(_pair((0.28, 0.21, 1.36)), _pair((0.56, 0.19, 1.38)), held="wands"),
    "crouching": _Pose(
        _pair((0.1, 0.25, 1.14)),
        _pair((0.34, 0.22, 1.0)),
        knees=_pair((0.17, 0.14, 0.45)),
        ankles=_pair((0.02, 0.14, 0.09)),
        pelvis=(-0.12, 0.75),
        lean=32.0,
    ),
    "carrying_box": _Pose(_pair((0.06, 0.24, 1.12)), _pair((0.32, 0.2, 1.08)), held="box"),
    "pointing": _Pose(
        elbows=((0.14, 0.46, 1.42), (-0.03, -0.25, 1.13)),
        hands=((0.33, 0.7, 1.45), (0.0, -0.26, 0.87)),
    ),
}


def _head(headwear: str, rgb: Rgb, skin: Rgb) -> Parts:
    """Head with 'hair', a 'cap' (brim forward) or a 'helmet', and ear defenders."""
    parts = [_ball(0.1, (0.015, 0, 1.62), skin, (1.0, 0.8, 1.12))]
    if headwear == "helmet":
        parts.append(_ball(0.118, (-0.005, 0, 1.655), rgb, (1.05, 0.9, 0.8)))
    else:
        parts.append(_ball(0.1, (-0.02, 0, 1.655), rgb, (1.0, 0.84, 0.95)))
    if headwear != "hair":
        parts.append(_box((0.1, 0.15, 0.015), (0.13, 0, 1.675), rgb))  # peak
    for y in (0.085, -0.085):
        parts.append(_cylinder(0.045, 0.05, (0.0, y, 1.62), BLACK, axis="y", sections=10))
    return parts


def _upper_body(pose: _Pose, vest: Rgb, shirt: Rgb, build: float) -> Parts:
    """Torso in a hi-vis vest, shoulders, arms and what the hands hold (upright frame)."""
    parts = [
        _cylinder(1.0, 0.42, (0, 0, 1.2), vest, stretch=(0.13 * build, 0.19 * build, 1)),
        _rod((0, -0.18, 1.39), (0, 0.18, 1.39), 0.08 * build, vest),
        _cylinder(0.05, 0.16, (0, 0, 1.45), SKIN[0]),
    ]
    for y in (0.18, -0.18):
        parts.append(_ball(0.08 * build, (0, y, 1.39), vest))
        parts.append(
            _box((0.2 * build, 0.035, 0.02), (0, y * 0.6, 1.39 + 0.075 * build), REFLECTIVE)
        )
    for z in (1.08, 1.26):
        parts.append(
            _cylinder(1.0, 0.04, (0, 0, z), REFLECTIVE, stretch=(0.134 * build, 0.194 * build, 1))
        )
    for side, (elbow, hand) in enumerate(zip(pose.elbows, pose.hands)):
        shoulder = (0.0, (0.2, -0.2)[side] * build, 1.4)
        parts += [
            _rod(shoulder, elbow, 0.048 * build, shirt),
            _ball(0.045 * build, elbow, shirt),
            _rod(elbow, hand, 0.042 * build, shirt),
            _ball(0.048, hand, FRAME),  # glove
        ]
        if pose.held == "wands":
            direction = np.subtract(hand, elbow) + np.array([0.2, 0.0, 0.0])
            direction /= np.linalg.norm(direction)
            grip = np.asarray(hand) + 0.1 * direction
            parts.append(_rod(hand, grip, 0.022, BLACK))
            parts.append(_rod(grip, grip + 0.32 * direction, 0.028, WAND))
    if pose.held == "box":
        parts.append(_box((0.36, 0.38, 0.3), (0.36, 0.0, 1.12), CARDBOARD))
    return parts


def _person(
    pose_name: str,
    vest: Rgb,
    height: float,
    build: float = 1.0,
    headwear: str = "helmet",
    head_rgb: Rgb = WHITE,
    shirt: Rgb = NAVY,
    skin: Rgb = SKIN[0],
) -> Parts:
    """Ground crew member facing +x, ``height`` tall when upright; ``build`` scales girth."""
    pose = _POSES[pose_name]
    upper = _upper_body(pose, vest, shirt, build) + _head(headwear, head_rgb, skin)
    hip_x, hip_z = pose.pelvis
    bend = (
        translation_matrix((hip_x, 0.0, hip_z))
        @ rotation_matrix(np.radians(pose.lean), (0, 1, 0))
        @ translation_matrix((0.0, 0.0, -0.92))
    )
    for part in upper:
        part.apply_transform(bend)
    parts = upper + [
        _cylinder(1.0, 0.2, (hip_x, 0, hip_z + 0.02), NAVY, stretch=(0.11 * build, 0.17 * build, 1))
    ]
    for side, (knee, ankle) in enumerate(zip(pose.knees, pose.ankles)):
        hip = (hip_x, (0.09, -0.09)[side] * build, hip_z)
        parts += [
            _rod(hip, knee, 0.075 * build, NAVY),
            _ball(0.06 * build, knee, NAVY),
            _rod(knee, ankle, 0.058 * build, NAVY),
            _box((0.27, 0.11, 0.11), (ankle[0] + 0.06, ankle[1], 0.055), BLACK),  # boot
        ]
    for part in parts:
        part.apply_scale(height / 1.75)
    return parts


# --- equipment -----------------------------------------------------------------------


def _trailer(
    length: float, width: float, deck: float, rgb: Rgb, wheel_radius: float = 0.2
) -> Parts:
    """Four-wheel towed chassis: deck top at ``deck``, drawbar with towing eye towards +x."""
    front = length / 2
    parts = _wheels((front - 0.35, -front + 0.35), width - 0.2, wheel_radius, 0.14)
    parts.append(_box((length, width, 0.12), (0, 0, deck - 0.06), rgb))
    eye = (front + 1.0, 0.0, deck - 0.1)
    for y in (0.3, -0.3):
        parts.append(_rod((front - 0.1, y, deck - 0.1), eye, 0.035, FRAME))
    parts.append(_ring(0.07, 0.02, eye, FRAME))
    return parts


def _cone(x: float, y: float) -> Parts:
    """Traffic cone, 0.75 m: weighted square base, orange body, two reflective collars."""
    parts = [
        _box((0.4, 0.4, 0.04), (x, y, 0.02), BLACK),
        _paint(
            trimesh.creation.cone(
                0.16, 0.75, sections=20, transform=translation_matrix((x, y, 0.04))
            ),
            ORANGE,
        ),
    ]
    for z, h in ((0.4, 0.1), (0.24, 0.08)):
        radius = 0.16 * (1 - (z + h / 2 - 0.04) / 0.75) + 0.008
        parts.append(_cylinder(radius, h, (x, y, z + h / 2), WHITE))
    return parts


def _traffic_cones(count: int, spacing: float = 1.4) -> Parts:
    parts: Parts = []
    for k in range(count):
        parts += _cone(k * spacing, 0.0)
    return parts


def _ld3(x: float = 0.0, base: float = 0.0) -> Parts:
    """LD3 container: 1.56 m base, 2.01 m over the sloped side, 1.53 m deep, 1.63 m tall."""
    left = x - 1.005
    contour = [
        (left, base),
        (left + 1.56, base),
        (left + 2.01, base + 0.5),
        (left + 2.01, base + 1.63),
        (left, base + 1.63),
    ]
    parts = [_prism(contour, 1.53, ALUMINIUM)]
    top = base + 1.63
    for dx in (0.3, 1.0, 1.7):  # roof ribs
        parts.append(_box((0.05, 1.5, 0.02), (left + dx, 0, top + 0.01), STEEL))
    parts += [
        _box((2.0, 0.05, 0.02), (x, 0.74, top + 0.01), STEEL),
        _box((2.0, 0.05, 0.02), (x, -0.74, top + 0.01), STEEL),
        _box((1.7, 0.02, 1.3), (x + 0.1, 0.77, base + 0.85), BLUE),  # door curtain
        _box((1.56, 1.53, 0.04), (left + 0.78, 0, base + 0.02), STEEL),  # base plate
    ]
    return parts


def _uld_dolly(load: bool) -> Parts:
    parts = _trailer(2.3, 1.8, 0.5, FRAME)
    parts += _rollers(-1.1, 1.1, 1.5, 0.52)
    for x in (1.12, -1.12):
        for y in (0.8, -0.8):
            parts.append(_box((0.08, 0.08, 0.25), (x, y, 0.62), RAIL_YELLOW))  # stops
    for y in (0.88, -0.88):
        parts.append(_box((2.3, 0.05, 0.1), (0, y, 0.55), RAIL_YELLOW))
    if load:
        parts += _ld3(0.0, 0.56)
    return parts


_BAG_COLOURS = (BLACK, NAVY, RED, STEEL, DARK_GREEN, PURPLE, BROWN, LIGHT_GREY, ORANGE)


def _baggage_cart(load: str) -> Parts:
    """Baggage cart with end frames and side rails; ``load``: 'empty', 'bags' or 'covered'."""
    parts = _trailer(3.0, 1.5, 0.5, STEEL)
    for y in np.linspace(-0.6, 0.6, 5):  # floor slats
        parts.append(_box((2.9, 0.12, 0.02), (0.0, y, 0.51), LIGHT_GREY))
    for x in (1.47, -1.47):  # end gates
        parts.append(_box((0.06, 1.5, 1.1), (x, 0.0, 1.05), FRAME))
    for y in (0.74, -0.74):
        parts.append(_rod((-1.5, y, 0.8), (1.5, y, 0.8), 0.035, RAIL_YELLOW))
    if load == "bags":
        k = 0
        for x in (-1.1, -0.38, 0.34, 1.06):
            for y in (0.36, -0.36):
                length, width, height = (
                    (0.7, 0.62, 0.66, 0.56)[k % 4],
                    0.46,
                    (0.28, 0.24, 0.3)[k % 3],
                )
                parts.append(
                    _box((length, width, height), (x, y, 0.5 + height / 2), _BAG_COLOURS[k % 9])
                )
                if k % 3 != 1:  # a second layer on most stacks
                    parts.append(
                        _box(
                            (0.55, 0.38, 0.22),
                            (x + 0.03, y - 0.02, 0.61 + height),
                            _BAG_COLOURS[(k + 4) % 9],
                        )
                    )
                k += 1
    elif load == "covered":
        parts.append(_box((3.1, 1.6, 0.05), (0.0, 0.0, 1.9), BLUE))
        for x in (-1.0, 0.0, 1.0):
            parts.append(_box((0.06, 1.6, 0.03), (x, 0.0, 1.93), LIGHT_GREY))  # roof bows
        parts.append(_box((3.1, 0.04, 0.6), (0.0, 0.78, 1.55), BLUE))  # rolled-up curtain
        for x in (1.5, -1.5):
            for y in (0.74, -0.74):
                parts.append(_rod((x, y, 0.5), (x, y, 1.88), 0.025, FRAME))
    return parts


def _water_barriers(count: int = 3) -> Parts:
    """Interlocking water-filled plastic barriers, alternately red and white."""
    profile = [(-0.25, 0.0), (0.25, 0.0), (0.2, 0.25), (0.09, 0.8), (-0.09, 0.8), (-0.2, 0.25)]
    parts: Parts = []
    for k in range(count):
        x = 1.85 * k
        parts.append(_prism(profile, 1.8, (RED, WHITE)[k % 2], axis="x", at=x))
        parts.append(_cylinder(0.06, 0.04, (x, 0.0, 0.82), (WHITE, RED)[k % 2]))  # filler cap
    return parts


def _ground_power_unit() -> Parts:
    parts = _trailer(2.4, 1.4, 0.45, FRAME, 0.22)
    parts += _generator(0.0, 0.45, 2.3, 1.35, 1.25, (220, 224, 226))
    parts.append(_ring(0.3, 0.04, (-0.55, 0.0, 1.75), BLACK))  # coiled 400 Hz cable
    parts.append(_ring(0.22, 0.04, (-0.55, 0.0, 1.8), BLACK))
    return parts


def _air_start_unit() -> Parts:
    parts = _trailer(3.0, 1.6, 0.45, FRAME, 0.25)
    parts += _generator(0.0, 0.45, 2.9, 1.55, 1.3, YELLOW)
    parts.append(_box((1.4, 1.3, 0.12), (-0.6, 0.0, 1.81), FRAME))  # hose basket
    for radius in (0.5, 0.32):  # coiled yellow air hose
        parts.append(_ring(radius, 0.09, (-0.6, 0.0, 1.96), (250, 215, 60)))
    parts.append(_cylinder(0.16, 0.5, (1.0, 0.0, 1.95), STEEL))  # air outlet
    return parts


def _wheel_chocks() -> Parts:
    """A pair of chocks joined by a rope, as placed fore and aft of a tyre."""
    parts = []
    for x in (0.6, -0.6):
        wedge = [(x - 0.22, 0.0), (x + 0.22, 0.0), (x + 0.1, 0.2), (x - 0.1, 0.2)]
        parts.append(_prism(wedge, 0.4, YELLOW))
    parts.append(_rod((-0.6, 0.18, 0.15), (0.6, 0.18, 0.15), 0.02, WHITE))  # rope
    parts.append(_rod((-0.6, -0.18, 0.15), (0.6, -0.18, 0.15), 0.02, WHITE))
    return parts


def _tow_bar() -> Parts:
    """Aircraft tow bar, yellow and black sections, on a wheeled carriage."""
    parts = []
    for k in range(9):
        x = -2.2 + 0.5 * k
        parts.append(_rod((x, 0, 0.4), (x + 0.5, 0, 0.4), 0.06, (YELLOW, BLACK)[k % 2]))
    parts += _wheels((-0.6,), 0.7, 0.2, 0.12)
    parts.append(_rod((-0.6, -0.35, 0.2), (-0.6, 0.35, 0.2), 0.03, FRAME))
    parts.append(_beam((-0.6, 0.0, 0.2), (-0.6, 0.0, 0.4), 0.06, FRAME))
    parts.append(_ring(0.12, 0.03, (2.4, 0.0, 0.4), FRAME))  # towing eye
    parts.append(_box((0.4, 0.35, 0.2), (-2.35, 0.0, 0.4), RED))  # aircraft head
    return parts


def _fire_extinguisher_trolley() -> Parts:
    parts = _wheels((-0.15,), 0.62, 0.22, 0.1)
    parts.append(_box((0.55, 0.5, 0.05), (0.05, 0.0, 0.1), FRAME))
    for y in (0.14, -0.14):
        parts.append(_cylinder(0.14, 0.95, (0.1, y, 0.6), RED))
        parts.append(_ball(0.14, (0.1, y, 1.07), RED, (1, 1, 0.5)))
        parts.append(_cylinder(0.03, 0.08, (0.1, y, 1.16), BLACK))
        parts.append(_ring(0.1, 0.02, (0.1, y, 0.65), BLACK))  # hose
    parts.append(_rod((-0.25, 0.25, 0.3), (-0.35, 0.25, 1.15), 0.02, FRAME))
    parts.append(_rod((-0.25, -0.25, 0.3), (-0.35, -0.25, 1.15), 0.02, FRAME))
    parts.append(_rod((-0.35, 0.25, 1.15), (-0.35, -0.25, 1.15), 0.02, FRAME))
    return parts


def _hydrant_dispenser_cart() -> Parts:
    parts = _trailer(3.6, 2.0, 0.6, WHITE, 0.3)
    parts += [
        _cylinder(0.35, 1.3, (-1.0, 0.0, 1.25), STEEL),  # filter/water separator vessel
        _ball(0.35, (-1.0, 0.0, 1.9), STEEL, (1, 1, 0.4)),
        _cylinder(0.35, 1.5, (0.3, 0.0, 1.0), RED, axis="y"),  # hose reel
        _box((0.6, 0.6, 0.9), (1.3, -0.6, 1.05), LIGHT_GREY),  # meter cabinet
        _box((1.2, 1.6, 0.08), (-0.6, 0.0, 2.2), STEEL),  # lift platform
        _ring(0.45, 0.06, (1.1, 0.45, 0.65), BLACK),  # hydrant intake hose
    ]
    parts += _railing((-1.2, 0.8, 2.2), (0.0, 0.8, 2.2), 1.0, RAIL_YELLOW, 2)
    parts += _railing((-1.2, -0.8, 2.2), (0.0, -0.8, 2.2), 1.0, RAIL_YELLOW, 2)
    parts.append(_rod((0.0, 0.8, 0.6), (0.0, 0.8, 2.15), 0.05, FRAME))
    return parts


def _pallet(z: float, dx: float, rgb: Rgb) -> Parts:
    """EUR pallet, 1.2 x 0.8 x 0.144 m: bottom boards, blocks, cross boards, slatted top."""
    parts = []
    for y in (-0.35, 0.0, 0.35):
        parts.append(_box((1.2, 0.1, 0.022), (dx, y, z + 0.011), rgb))
        for x in (-0.55, 0.0, 0.55):
            parts.append(_box((0.1, 0.1, 0.078), (dx + x, y, z + 0.061), rgb))
    for x in (-0.55, 0.0, 0.55):
        parts.append(_box((0.145, 0.8, 0.022), (dx + x, 0.0, z + 0.111), (140, 104, 64)))
    for y in np.linspace(-0.345, 0.345, 5):
        parts.append(_box((1.2, 0.11, 0.022), (dx, y, z + 0.133), rgb))
    return parts


def _pallet_stack(count: int = 6) -> Parts:
    parts: Parts = []
    for k in range(count):
        parts += _pallet(0.144 * k, 0.02 * (k % 2), (WOOD, (160, 120, 76))[k % 2])
    return parts


def _fence_segment(panels: int = 2, panel_len: float = 3.4) -> Parts:
    """Temporary mesh fence: framed mesh panels on concrete feet."""
    parts = []
    start = -panels * panel_len / 2
    for k in range(panels + 1):
        x = start + k * panel_len
        parts.append(_box((0.7, 0.22, 0.14), (x, 0.0, 0.07), FRAME))  # rubber foot
    for k in range(panels):
        x0 = start + k * panel_len + 0.03
        x1 = x0 + panel_len - 0.06
        for z in (0.15, 2.0):
            parts.append(_rod((x0, 0, z), (x1, 0, z), 0.025, ALUMINIUM))
        for x in np.linspace(x0, x1, 13):
            parts.append(_box((0.008, 0.008, 1.85), (x, 0, 1.075), ALUMINIUM))
        for z in np.linspace(0.3, 1.85, 8):
            parts.append(_box((x1 - x0, 0.008, 0.008), ((x0 + x1) / 2, 0, z), ALUMINIUM))
        for x in (x0, x1):
            parts.append(_rod((x, 0, 0.14), (x, 0, 2.0), 0.02, ALUMINIUM))
        parts.append(_box((1.2, 0.02, 0.5), ((x0 + x1) / 2, 0.02, 1.1), ORANGE))  # banner
    return parts


# --- catalogue -----------------------------------------------------------------------

_Builder = Callable[[], Parts]


def _liveries(
    kind: str, builder: Callable[[Rgb], Parts], *colours: str
) -> dict[str, tuple[str, _Builder]]:
    return {f"{kind}_{c}": ("vehicle", partial(builder, LIVERIES[c])) for c in colours}


_VEHICLES: dict[str, tuple[str, _Builder]] = {
    **_liveries("baggage_tractor", _baggage_tractor, "yellow", "blue", "white"),
    **_liveries("fuel_truck", _fuel_truck, "white", "red"),
    **_liveries("catering_truck", _catering_truck, "white", "blue"),
    **_liveries("pushback_tug", _pushback_tug, "yellow", "white"),
    **_liveries("belt_loader", _belt_loader, "yellow", "orange"),
    **_liveries("stairs_truck", _stairs_truck, "white", "yellow"),
    **_liveries("apron_bus", _apron_bus, "blue", "white"),
    "ops_car_white": ("vehicle", partial(_car, WHITE, "light_bar")),
    "follow_me_car_yellow": ("vehicle", partial(_car, YELLOW, "checker")),
    **_liveries("pickup", _pickup, "white", "orange"),
    **_liveries("van", _van, "white", "yellow"),
    **_liveries("deicing_truck", _deicing_truck, "orange"),
    "lavatory_truck_blue": ("vehicle", partial(_service_truck, BLUE, "cylinder", BLUE)),
    "water_truck_white": ("vehicle", partial(_service_truck, WHITE, "box", BLUE)),
    **_liveries("gpu_truck", _gpu_truck, "yellow"),
    **_liveries("fire_truck", _fire_truck, "red"),
    **_liveries("ambulance", _ambulance, "white"),
    **_liveries("forklift", _forklift, "yellow", "orange"),
    **_liveries("container_loader", _container_loader, "yellow", "white"),
}

_VESTS: dict[str, Rgb] = {"yellow": HIVIS_YELLOW, "orange": HIVIS_ORANGE, "lime": HIVIS_LIME}
DARK_HAIR: Rgb = (28, 24, 21)
BROWN_HAIR: Rgb = (90, 60, 30)
GREY_SHIRT: Rgb = (90, 90, 96)

# name: (pose, height m, build, headwear, its colour, sleeves, skin tone); the vest colour
# is the second word of the name.
_CREW: dict[str, tuple[str, float, float, str, Rgb, Rgb, int]] = {
    "marshaller_orange_wands_up": ("wands_up", 1.76, 1.0, "cap", NAVY, NAVY, 0),
    "marshaller_yellow_wands_up": ("wands_up", 1.68, 0.95, "helmet", WHITE, HIVIS_YELLOW, 1),
    "marshaller_lime_wands_forward": ("wands_forward", 1.82, 1.05, "helmet", WHITE, NAVY, 2),
    "marshaller_orange_wands_forward": ("wands_forward", 1.72, 1.0, "hair", BROWN_HAIR, NAVY, 0),
    "crew_yellow_standing": ("standing", 1.75, 1.0, "helmet", YELLOW, NAVY, 0),
    "crew_orange_standing_tall": ("standing", 1.9, 1.12, "hair", DARK_HAIR, NAVY, 2),
    "crew_lime_standing_small": ("standing", 1.62, 0.9, "cap", BLUE, GREY_SHIRT, 1),
    "crew_yellow_walking": ("walking", 1.78, 1.0, "hair", BROWN_HAIR, NAVY, 1),
    "crew_orange_walking": ("walking", 1.66, 0.92, "helmet", WHITE, HIVIS_ORANGE, 0),
    "crew_lime_walking_tall": ("walking", 1.88, 1.1, "cap", BLACK, NAVY, 2),
    "crew_orange_crouching": ("crouching", 1.8, 1.05, "helmet", WHITE, NAVY, 1),
    "crew_yellow_crouching": ("crouching", 1.86, 1.0, "cap", RED, GREY_SHIRT, 0),
    "crew_lime_carrying_box": ("carrying_box", 1.74, 1.0, "hair", DARK_HAIR, NAVY, 1),
    "crew_orange_carrying_box": ("carrying_box", 1.7, 1.08, "cap", NAVY, NAVY, 2),
    "crew_yellow_pointing": ("pointing", 1.73, 0.97, "helmet", ORANGE, NAVY, 2),
}

_PEOPLE: dict[str, tuple[str, _Builder]] = {
    name: (
        "person",
        partial(
            _person,
            pose,
            _VESTS[name.split("_")[1]],
            height,
            build,
            headwear,
            head_rgb,
            sleeves,
            SKIN[skin],
        ),
    )
    for name, (pose, height, build, headwear, head_rgb, sleeves, skin) in _CREW.items()
}

_EQUIPMENT: dict[str, tuple[str, _Builder]] = {
    name: ("equipment", builder)
    for name, builder in (
        ("traffic_cone", partial(_traffic_cones, 1)),
        ("traffic_cone_row", partial(_traffic_cones, 5)),
        ("uld_ld3", _ld3),
        ("uld_ld3_on_dolly", partial(_uld_dolly, True)),
        ("uld_dolly_empty", partial(_uld_dolly, False)),
        ("baggage_cart_empty", partial(_baggage_cart, "empty")),
        ("baggage_cart_loaded", partial(_baggage_cart, "bags")),
        ("baggage_cart_covered", partial(_baggage_cart, "covered")),
        ("water_barrier_row", _water_barriers),
        ("ground_power_unit", _ground_power_unit),
        ("air_start_unit", _air_start_unit),
        ("wheel_chocks", _wheel_chocks),
        ("tow_bar", _tow_bar),
        ("fire_extinguisher_trolley", _fire_extinguisher_trolley),
        ("hydrant_dispenser_cart", _hydrant_dispenser_cart),
        ("pallet_stack", _pallet_stack),
        ("fence_segment", _fence_segment),
    )
}

_CATALOG: dict[str, tuple[str, _Builder]] = {**_VEHICLES, **_PEOPLE, **_EQUIPMENT}

OCCLUDER_NAMES: tuple[str, ...] = tuple(_CATALOG)


def build_occluder(name: str) -> Occluder:
    """Build one occluder asset.

    Parameters
    ----------
    name : str
        One of ``OCCLUDER_NAMES``.

    Returns
    -------
    Occluder
        A fresh mesh (metres, z up, on z = 0, centred in x-y, face colours set).

    Raises
    ------
    ValueError
        If ``name`` is not a known occluder.
    """
    if name not in _CATALOG:
        raise ValueError(
            f"name: unknown occluder {name!r}; expected one of {', '.join(OCCLUDER_NAMES)}"
        )
    family, builder = _CATALOG[name]
    return Occluder(name=name, family=family, mesh=_assemble(builder()))


def occluder_catalog(family: str | None = None) -> list[Occluder]:
    """Build every occluder asset, or those of one family.

    Parameters
    ----------
    family : str or None
        One of ``FAMILIES``, or None for all assets.

    Returns
    -------
    list of Occluder
        In ``OCCLUDER_NAMES`` order.

    Raises
    ------
    ValueError
        If ``family`` is not one of ``FAMILIES``.
    """
    if family is not None and family not in FAMILIES:
        raise ValueError(f"family: unknown occluder family {family!r}; expected one of {FAMILIES}")
    return [
        build_occluder(name)
        for name in OCCLUDER_NAMES
        if family is None or _CATALOG[name][0] == family
    ]
