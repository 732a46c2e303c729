"""Parametric airliner meshes with their 23 keypoints, and loading a user's mesh.

Object frame (the study's, see :mod:`data_gen.keypoints`): x forward (towards the nose),
y to the left wing, z up, origin on the fuselage axis near mid-length; metres.

An airplane is described by an :class:`AirplaneGeometry` (fuselage, wing, engines,
horizontal stabiliser, fin and livery); :func:`airplane_from_geometry` turns it into a
coloured triangle mesh (per-face RGBA) and computes the keypoints from that geometry:
each keypoint gets an (x, y) anchor from the parametric description (slightly inside
an edge, e.g. 5 cm behind a leading edge) and its z from a ray cast straight down onto
the mesh, first hit, so every keypoint lies on the top-most surface, visible from above.
The parts intersect each other (no boolean union): the mesh is meant for a rasteriser.

``build_airplane('airliner')`` is the study's default airplane, whose keypoints are the
table in :mod:`data_gen.keypoints`. ``load_airplane`` reads a user's mesh and keypoint
JSON instead, ``save_airplane`` writes both.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np
import trimesh

from data_gen.keypoints import KEYPOINT_NAMES
from kpstudy.io import write_bytes_atomic, write_text_atomic

RGB = tuple[int, int, int]

VARIANTS: tuple[str, ...] = ("airliner", "swept", "stretched")

#: Part names, indexed by ``Airplane.part_ids``.
PART_NAMES: tuple[str, ...] = (
    "fuselage",
    "wing_left",
    "wing_right",
    "nacelle_left",
    "nacelle_right",
    "pylon_left",
    "pylon_right",
    "stabiliser_left",
    "stabiliser_right",
    "fin",
)

#: Colour of a loaded mesh that has none (RGBA).
DEFAULT_RGBA = (190, 192, 196, 255)

#: Largest distance, metres, of a loaded keypoint from the mesh surface.
MAX_KEYPOINT_DISTANCE = 0.25

#: Smallest extent of a loaded airplane's keypoints (their bounding box's longest side),
#: a fraction of the mesh's: the named keypoints run from nose to tail and tip to tip.
MIN_KEYPOINT_SPAN = 0.25

#: Largest collinearity of the keypoints seen from above: the smaller singular value of
#: their centred (x, y) must exceed this fraction of the larger (PnP needs 2-D images).
MIN_KEYPOINT_SPREAD_RATIO = 0.01

_INSET = 0.05  # keypoint anchors sit this far inside an edge, metres


def _lerp(s, s0, v0, s1, v1):
    """The line through (s0, v0) and (s1, v1) at ``s`` (extrapolated outside)."""
    return v0 + (np.asarray(s, dtype=np.float64) - s0) * (v1 - v0) / (s1 - s0)


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Livery:
    """Colours (RGB, 0–255) of an airplane's paint scheme.

    ``accent`` paints the fin, ``accent2`` the cheatline and a band across the fin;
    ``tail_wrap_x`` (if set) extends the accent over the fuselage crown aft of that x.
    """

    accent: RGB
    accent2: RGB
    nacelle: RGB
    crown: RGB = (244, 244, 242)
    belly: RGB = (200, 203, 208)
    wing: RGB = (196, 199, 204)
    control: RGB = (136, 141, 148)
    walkway: RGB = (176, 179, 184)
    window: RGB = (24, 27, 34)
    metal: RGB = (214, 216, 220)
    intake: RGB = (52, 55, 61)
    tail_wrap_x: float | None = None


@dataclass(frozen=True)
class FuselageParams:
    """A tube with an elliptic nose cone and a tail cone that rises towards the tail.

    Attributes
    ----------
    x_nose, x_tail : float
        x of the nose tip and of the tail-cone end (the APU exhaust).
    radius : float
        Radius of the constant section (half the fuselage width and height).
    nose_length : float
        Length of the nose cone.
    z_nose_tip : float
        Height of the nose tip (below the axis on an airliner).
    tail_cone_start : float
        x where the tail cone begins.
    tail_top_z, tail_bottom_z, tail_half_width : float
        Section of the tail-cone end.
    x_cockpit : float
        x of the cockpit window band on the centreline (the ``cockpit`` keypoint).
    kp_offset : float
        ``fuselage_front`` / ``fuselage_rear`` keypoints lie at x = ±kp_offset.
    n_around : int
        Segments around the fuselage (a multiple of 4).
    """

    x_nose: float
    x_tail: float
    radius: float
    nose_length: float
    z_nose_tip: float
    tail_cone_start: float
    tail_top_z: float
    tail_bottom_z: float
    tail_half_width: float
    x_cockpit: float
    kp_offset: float
    n_around: int = 40


@dataclass(frozen=True)
class SurfaceParams:
    """A swept, tapered lifting surface with a NACA four-digit section (one side).

    The span coordinate ``s`` is y for a horizontal surface and z for a vertical one.
    The planform is given at two keypoint stations: the root station (where the surface
    leaves the fuselage) and the tip; the panel starts further in, at ``inner_station``.

    Attributes
    ----------
    root_le, root_chord, root_station : float
        Leading-edge x, chord and span coordinate of the root station.
    tip_le, tip_chord, tip_station : float
        The same at the tip.
    inner_station : float
        Span coordinate where the panel starts (inside the fuselage).
    offset : float
        Height (z for horizontal, y for vertical surfaces) of the chord plane at the
        root station.
    dihedral_deg : float
        Dihedral angle (horizontal surfaces).
    thickness : (float, float)
        Thickness-to-chord ratio at root and tip.
    camber : float
        Maximum camber as a fraction of the chord (at 40 % chord).
    te_kink : (float, float) or None
        (span coordinate, trailing-edge x) of a trailing-edge kink.
    vertical : bool
        Span along z (a fin, a pylon) instead of y.
    n_span : int
        Number of evenly spaced span stations (band edges are added to them).
    """

    root_le: float
    root_chord: float
    root_station: float
    tip_le: float
    tip_chord: float
    tip_station: float
    inner_station: float
    offset: float = 0.0
    dihedral_deg: float = 0.0
    thickness: tuple[float, float] = (0.12, 0.10)
    camber: float = 0.0
    te_kink: tuple[float, float] | None = None
    vertical: bool = False
    n_span: int = 12

    def leading_edge(self, s):
        """Leading-edge x at span coordinate(s) ``s`` (linear, extrapolated inwards)."""
        return _lerp(s, self.root_station, self.root_le, self.tip_station, self.tip_le)

    def trailing_edge(self, s):
        """Trailing-edge x at span coordinate(s) ``s`` (piecewise linear)."""
        s = np.asarray(s, dtype=np.float64)
        te_root = self.root_le - self.root_chord
        te_tip = self.tip_le - self.tip_chord
        if self.te_kink is None:
            return _lerp(s, self.root_station, te_root, self.tip_station, te_tip)
        sk, xk = self.te_kink
        return np.where(
            s <= sk,
            _lerp(s, self.root_station, te_root, sk, xk),
            _lerp(s, sk, xk, self.tip_station, te_tip),
        )


@dataclass(frozen=True)
class EngineParams:
    """A turbofan nacelle under the left wing (the right one is its mirror image).

    Attributes
    ----------
    y : float
        Lateral position of the nacelle axis.
    x_front : float
        x of the intake lip's most forward point.
    z_axis : float
        Height of the nacelle axis.
    length : float
        Length from the intake lip to the fan nozzle.
    radius : float
        Largest outer radius.
    lip_radius : float
        Outer radius of the intake lip.
    n_around : int
        Segments around the nacelle (a multiple of 4).
    """

    y: float
    x_front: float
    z_axis: float
    length: float
    radius: float
    lip_radius: float
    n_around: int = 32


@dataclass(frozen=True)
class AirplaneGeometry:
    """Everything that defines one airplane variant (metres, degrees).

    ``fin_root_kp_dx`` places the ``fin_root`` keypoint on the fin's leading edge, that
    far aft of the fin's root leading edge (which lies inside the fuselage).
    ``gear_height`` is the distance from the fuselage bottom down to the ground.
    """

    fuselage: FuselageParams
    wing: SurfaceParams
    engine: EngineParams
    stabiliser: SurfaceParams
    fin: SurfaceParams
    livery: Livery
    fin_root_kp_dx: float = 1.1
    gear_height: float = 1.52


# ------------------------------------------------------------------------------ variants

# The default's edges are placed so that its keypoint anchors (5 cm inside the edges) fall
# on round coordinates; its keypoints are the table in data_gen.keypoints.

_AIRLINER = AirplaneGeometry(
    fuselage=FuselageParams(
        x_nose=18.85,
        x_tail=-19.45,
        radius=1.98,
        nose_length=5.0,
        z_nose_tip=-0.1,
        tail_cone_start=-7.0,
        tail_top_z=1.15,
        tail_bottom_z=0.55,
        tail_half_width=0.3,
        x_cockpit=16.2,
        kp_offset=10.0,
    ),
    wing=SurfaceParams(
        root_le=4.55,
        root_chord=6.1,
        root_station=2.0,
        tip_le=-3.45,
        tip_chord=1.8,
        tip_station=17.95,
        inner_station=0.6,
        offset=0.2,
        dihedral_deg=3.4,
        thickness=(0.13, 0.10),
        camber=0.02,
        te_kink=(6.3, -2.1),
        n_span=14,
    ),
    engine=EngineParams(
        y=5.8, x_front=6.55, z_axis=-1.35, length=4.3, radius=1.05, lip_radius=0.97
    ),
    stabiliser=SurfaceParams(
        root_le=-13.95,
        root_chord=3.8,
        root_station=1.0,
        tip_le=-17.55,
        tip_chord=1.4,
        tip_station=6.25,
        inner_station=0.2,
        offset=1.35,
        dihedral_deg=6.0,
        thickness=(0.11, 0.09),
        n_span=6,
    ),
    fin=SurfaceParams(
        root_le=-11.7,
        root_chord=6.6,
        root_station=1.0,
        tip_le=-17.65,
        tip_chord=1.7,
        tip_station=8.2,
        inner_station=1.0,
        thickness=(0.11, 0.09),
        vertical=True,
        n_span=8,
    ),
    livery=Livery(accent=(22, 48, 120), accent2=(232, 162, 24), nacelle=(22, 48, 120)),
)

_SWEPT = replace(
    _AIRLINER,
    wing=replace(
        _AIRLINER.wing,
        root_le=5.3,
        root_chord=6.4,
        tip_le=-7.1,
        tip_chord=1.5,
        tip_station=20.0,
        dihedral_deg=5.0,
        thickness=(0.12, 0.09),
        te_kink=(7.0, -2.0),
    ),
    engine=replace(_AIRLINER.engine, y=6.3, x_front=6.5),
    stabiliser=replace(
        _AIRLINER.stabiliser,
        root_le=-13.8,
        root_chord=3.9,
        tip_le=-18.0,
        tip_chord=1.3,
        tip_station=6.35,
    ),
    fin=replace(
        _AIRLINER.fin,
        root_le=-11.5,
        root_chord=6.8,
        tip_le=-17.8,
        tip_chord=1.55,
        tip_station=8.4,
    ),
    livery=Livery(
        accent=(196, 26, 36), accent2=(40, 40, 48), nacelle=(240, 240, 238), tail_wrap_x=-12.5
    ),
)

_STRETCH = -2.7  # the stretched variant's tail moves aft by this much
_STRETCHED = replace(
    _AIRLINER,
    fuselage=replace(
        _AIRLINER.fuselage,
        x_nose=21.95,
        x_tail=-19.45 + _STRETCH,
        tail_cone_start=-7.0 + _STRETCH,
        x_cockpit=19.3,
        kp_offset=11.0,
    ),
    wing=replace(
        _AIRLINER.wing,
        root_le=3.4,
        root_chord=6.3,
        tip_le=-4.6,
        tip_chord=1.8,
        tip_station=18.0,
        te_kink=(6.4, -3.3),
    ),
    engine=replace(_AIRLINER.engine, y=5.9, x_front=5.5),
    stabiliser=replace(_AIRLINER.stabiliser, root_le=-13.95 + _STRETCH, tip_le=-17.55 + _STRETCH),
    fin=replace(_AIRLINER.fin, root_le=-11.7 + _STRETCH, tip_le=-17.65 + _STRETCH),
    livery=Livery(accent=(0, 122, 112), accent2=(236, 178, 36), nacelle=(0, 122, 112)),
)

#: Geometry of each variant in ``VARIANTS``.
GEOMETRIES: Mapping[str, AirplaneGeometry] = MappingProxyType(
    {"airliner": _AIRLINER, "swept": _SWEPT, "stretched": _STRETCHED}
)


# ------------------------------------------------------------------------- mesh building


@dataclass(frozen=True)
class _Part:
    """One closed, outward-oriented part: vertices (V, 3), faces (F, 3), colours (F, 4)."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray

    def mirrored(self) -> _Part:
        """The mirror image about the x-z plane (y → −y), still outward-oriented."""
        return _Part(self.vertices * [1.0, -1.0, 1.0], self.faces[:, ::-1].copy(), self.colors)


def _rgba(rgb: RGB, n: int) -> np.ndarray:
    return np.tile(np.array([*rgb, 255], dtype=np.uint8), (n, 1))


def _loft(rings: np.ndarray, start, end):
    """Triangulate a stack of closed rings into one closed surface.

    Parameters
    ----------
    rings : ndarray, shape (S, P, 3)
        Closed rings (the last point connects back to the first).
    start, end : ndarray (3,) or "fan" or "strip"
        Cap of the first / last ring: a pole point to fan to, "fan" to the ring's
        centroid, or "strip" for an airfoil loop (upper surface trailing → leading
        edge, then lower surface leading → trailing edge, P even).

    Returns
    -------
    vertices : ndarray, shape (V, 3)
    faces : ndarray, shape (F, 3)
    row : ndarray, shape (F,)
        Gap between rings i and i + 1 of a side face; −1 for the start cap and S − 1
        for the end cap.
    col : ndarray, shape (F,)
        Ring segment j (from point j to j + 1) of a side face; for a cap the fan
        segment or the strip quad.
    """
    S, P, _ = rings.shape
    vertices = [rings.reshape(-1, 3)]
    i, j = np.meshgrid(np.arange(S - 1), np.arange(P), indexing="ij")
    a, b = i * P + j, i * P + (j + 1) % P
    c, d = (i + 1) * P + (j + 1) % P, (i + 1) * P + j
    faces = [np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3)]
    row = [np.repeat(i.ravel(), 2)]
    col = [np.repeat(j.ravel(), 2)]
    n_vertices = S * P
    for ring_index, cap, label in ((0, start, -1), (S - 1, end, S - 1)):
        base = ring_index * P
        if isinstance(cap, str) and cap == "strip":
            n = P // 2
            k = np.arange(n - 1)
            up0, up1, lo0, lo1 = base + n - 1 - k, base + n - 2 - k, base + n + k, base + n + k + 1
            tri = np.concatenate([np.stack([up1, up0, lo0], -1), np.stack([up1, lo0, lo1], -1)])
            cap_col = np.concatenate([k, k])
        else:
            point = rings[ring_index].mean(0) if isinstance(cap, str) else np.asarray(cap)
            vertices.append(point[None])
            ring = base + np.arange(P)
            tri = np.stack([np.full(P, n_vertices), ring, np.roll(ring, -1)], -1)
            n_vertices += 1
            cap_col = np.arange(P)
        faces.append(tri[:, ::-1] if label == -1 else tri)  # start cap faces backwards
        row.append(np.full(len(tri), label))
        col.append(cap_col)
    return np.concatenate(vertices), np.concatenate(faces), np.concatenate(row), np.concatenate(col)


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` flipped if needed so that the closed surface encloses positive volume."""
    volume = trimesh.Trimesh(vertices, faces, process=False).volume
    return faces if volume > 0 else faces[:, ::-1].copy()


# fuselage -----------------------------------------------------------------------------

_NOSE_EXP = (2.0, 2.6, 2.2)  # superellipse exponents of the nose's top, bottom, width
_TAIL_EXP = (1.7, 1.1, 1.25)  # how the tail cone's top, bottom, width approach the end


def _fuselage_profile(f: FuselageParams, x: np.ndarray):
    """Top z, bottom z, half-width and widest-point z of the fuselage at stations ``x``."""
    R = f.radius
    top, bottom, width, zc = (np.zeros_like(x) for _ in range(4))
    top[:], bottom[:], width[:] = R, -R, R
    nose = x > f.x_nose - f.nose_length
    s = (x[nose] - (f.x_nose - f.nose_length)) / f.nose_length
    zt = f.z_nose_tip
    p_top, p_bottom, p_width = _NOSE_EXP
    top[nose] = zt + (R - zt) * (1 - s**p_top) ** (1 / p_top)
    bottom[nose] = zt - (R + zt) * (1 - s**p_bottom) ** (1 / p_bottom)
    width[nose] = R * (1 - s**p_width) ** (1 / p_width)
    zc[nose] = zt * s**2
    tail = x < f.tail_cone_start
    u = (f.tail_cone_start - x[tail]) / (f.tail_cone_start - f.x_tail)
    q_top, q_bottom, q_width = _TAIL_EXP
    top[tail] = R - (R - f.tail_top_z) * u**q_top
    bottom[tail] = -R + (f.tail_bottom_z + R) * u**q_bottom
    width[tail] = R - (R - f.tail_half_width) * u**q_width
    zc[tail] = (top[tail] + bottom[tail]) / 2
    return top, bottom, width, zc


def _fuselage(f: FuselageParams, livery: Livery) -> _Part:
    n = f.n_around
    x_nose_start = f.x_nose - f.nose_length
    nose_s = np.sin(np.pi / 2 * np.linspace(0, 1, 40))[:-1]
    stations = np.unique(
        np.round(
            np.concatenate(
                [
                    np.linspace(f.x_tail, f.tail_cone_start, 19),
                    np.linspace(f.tail_cone_start, x_nose_start, 24),
                    x_nose_start + f.nose_length * np.append(nose_s, 0.998),
                    np.arange(f.x_cockpit - 0.85, f.x_cockpit + 0.35, 0.06),  # window band
                ]
            ),
            9,
        )
    )
    top, bottom, width, zc = _fuselage_profile(f, stations)
    # Vertices at angles phi = (k + 1/2)·2π/n from +y towards +z, pushed out by
    # 1/cos(π/n) so that the faces on top, bottom and sides touch the profile exactly.
    phi = (np.arange(n) + 0.5) * 2 * np.pi / n
    grow = 1 / np.cos(np.pi / n)
    up = np.sin(phi) > 0
    semi = np.where(up, (top - zc)[:, None], (zc - bottom)[:, None])
    rings = np.stack(
        [
            np.broadcast_to(stations[:, None], (len(stations), n)),
            width[:, None] * np.cos(phi) * grow,
            zc[:, None] + semi * np.sin(phi) * grow,
        ],
        -1,
    )
    tip = np.array([f.x_nose, 0.0, f.z_nose_tip])
    vertices, faces, row, col = _loft(rings, "fan", tip)
    faces = _outward(vertices, faces)

    # colour by the face's station x and its angle from the top (0 top, π bottom)
    x_mid = np.where(row < 0, f.x_tail, np.where(row >= len(stations) - 1, f.x_nose, 0.0))
    side = (row >= 0) & (row < len(stations) - 1)
    x_mid[side] = (stations[row[side]] + stations[row[side] + 1]) / 2
    alpha = np.abs(np.angle(np.exp(1j * (np.pi / 2 - (col + 1) * 2 * np.pi / n))))
    alpha_deg = np.degrees(alpha)
    colors = _rgba(livery.crown, len(faces))
    colors[alpha_deg > 100] = [*livery.belly, 255]
    cheat = (alpha_deg > 64) & (alpha_deg < 77) & (x_mid > f.tail_cone_start - 4)
    cheat &= x_mid < x_nose_start + 1.0
    colors[cheat] = [*livery.accent2, 255]
    if livery.tail_wrap_x is not None:
        wrap = (x_mid < livery.tail_wrap_x) & (alpha_deg < 100)
        colors[wrap] = [*livery.accent, 255]
    # cockpit window band: crosses the centreline at x_cockpit, sweeps back on the sides
    q = (alpha_deg / 72.0) ** 2
    window = (alpha_deg < 72) & (x_mid < f.x_cockpit + 0.3 - 0.45 * q)
    window &= x_mid > f.x_cockpit - 0.25 - 0.6 * q
    colors[window & side] = [*livery.window, 255]
    colors[row < 0] = [*livery.intake, 255]  # APU exhaust
    return _Part(vertices, faces, colors)


# lifting surfaces ---------------------------------------------------------------------

# chordwise stations of the section; 0.002 leaves a blunt leading-edge strip
_XC = np.array(
    [
        0.002,
        0.01,
        0.025,
        0.05,
        0.08,
        0.12,
        0.17,
        0.25,
        0.33,
        0.42,
        0.5,
        0.55,
        0.6,
        0.68,
        0.75,
        0.82,
        0.9,
        0.96,
        1.0,
    ]
)


def _naca(xc: np.ndarray, t, m: float, p: float = 0.4):
    """Half-thickness and camber line of a NACA four-digit section, in chords."""
    yt = (
        5
        * t
        * (0.2969 * np.sqrt(xc) - 0.1260 * xc - 0.3516 * xc**2 + 0.2843 * xc**3 - 0.1015 * xc**4)
    )
    yc = np.where(
        xc < p,
        m / p**2 * (2 * p * xc - xc**2),
        m / (1 - p) ** 2 * ((1 - 2 * p) + 2 * p * xc - xc**2),
    )
    return yt, yc


def _surface(p: SurfaceParams, extra_stations=()):
    """Rings of a lifting surface and each face's span, chord fraction and side.

    Returns
    -------
    vertices, faces : ndarray
    s_mid : ndarray, shape (F,)
        Span coordinate of the face.
    xc_mid : ndarray, shape (F,)
        Chord fraction of the face (0 leading, 1 trailing edge).
    side : ndarray, shape (F,)
        +1 upper (or left) surface, −1 lower (right), 0 leading/trailing-edge strip,
        2 end caps.
    """
    lo, hi = p.inner_station, p.tip_station
    s = [np.linspace(lo, hi, p.n_span), [p.root_station], list(extra_stations)]
    if p.te_kink is not None:
        s.append([p.te_kink[0]])
    s = np.unique(np.round(np.concatenate(s), 9))
    s = s[(s >= lo) & (s <= hi)]
    s = s[np.append(np.diff(s) > 0.05, True) | (s == hi)]
    le, te = p.leading_edge(s), p.trailing_edge(s)
    chord = le - te
    t = np.interp(s, [p.root_station, p.tip_station], p.thickness)
    offset = p.offset + (s - p.root_station) * np.tan(np.radians(p.dihedral_deg))
    xc = np.concatenate([_XC[::-1], _XC])
    sign = np.concatenate([np.ones(len(_XC)), -np.ones(len(_XC))])
    yt, yc = _naca(xc[None], t[:, None], p.camber)
    h = offset[:, None] + chord[:, None] * (yc + sign * yt)
    x = le[:, None] - chord[:, None] * xc
    span = np.broadcast_to(s[:, None], x.shape)
    rings = np.stack([x, h, span] if p.vertical else [x, span, h], -1)
    vertices, faces, row, col = _loft(rings, "strip", "strip")
    faces = _outward(vertices, faces)

    P = len(xc)
    cap = (row < 0) | (row >= len(s) - 1)
    s_mid = np.where(row < 0, s[0], s[-1]).astype(np.float64)
    s_mid[~cap] = (s[row[~cap]] + s[row[~cap] + 1]) / 2
    k = np.minimum(col, len(_XC) - 2)  # strip quad of a cap face
    xc_mid = np.where(cap, (_XC[k] + _XC[k + 1]) / 2, (xc[col] + xc[(col + 1) % P]) / 2)
    side = np.where(sign[col] == sign[(col + 1) % P], sign[col], 0.0)
    side[cap] = 2
    return vertices, faces, s_mid, xc_mid, side


def _wing(w: SurfaceParams, livery: Livery) -> _Part:
    span = w.tip_station
    aileron = (0.72 * span, 0.95 * span)
    walkway = (w.root_station + 0.4, w.root_station + 3.2)
    vertices, faces, s, xc, side = _surface(w, (*aileron, *walkway))
    colors = _rgba(livery.wing, len(faces))
    upper = side == 1
    colors[upper & (xc < 0.06)] = [*livery.metal, 255]  # slats
    band = upper & (xc > 0.75) & (s > w.root_station) & (s < aileron[1])
    colors[band] = [*livery.control, 255]  # flaps and ailerons
    spoiler = upper & (xc > 0.6) & (xc < 0.75) & (s > w.root_station) & (s < aileron[0])
    colors[spoiler] = [*livery.walkway, 255]
    walk = upper & (xc > 0.25) & (xc < 0.55) & (s > walkway[0]) & (s < walkway[1])
    colors[walk] = [*livery.walkway, 255]
    colors[side == -1] = [*livery.belly, 255]
    return _Part(vertices, faces, colors)


def _stabiliser(hs: SurfaceParams, livery: Livery) -> _Part:
    vertices, faces, s, xc, side = _surface(hs)
    colors = _rgba(livery.wing, len(faces))
    colors[(side == 1) & (xc > 0.7)] = [*livery.control, 255]  # elevator
    return _Part(vertices, faces, colors)


def _fin(fin: SurfaceParams, livery: Livery) -> _Part:
    height = fin.tip_station - fin.root_station
    band = (fin.root_station + 0.55 * height, fin.root_station + 0.7 * height)
    vertices, faces, s, xc, side = _surface(fin, band)
    colors = _rgba(livery.accent, len(faces))
    colors[(s > band[0]) & (s < band[1]) & (side != 2)] = [*livery.accent2, 255]
    return _Part(vertices, faces, colors)


def _pylon(g: AirplaneGeometry) -> _Part:
    e, w = g.engine, g.wing
    wing_le = float(w.leading_edge(e.y))
    wing_z = w.offset + (e.y - w.root_station) * np.tan(np.radians(w.dihedral_deg))
    root_chord = e.length + 0.4
    tip_chord = 0.6 * float(wing_le - w.trailing_edge(e.y))
    p = SurfaceParams(
        root_le=e.x_front - 0.9,
        root_chord=root_chord,
        root_station=e.z_axis + 0.6 * e.radius,
        tip_le=wing_le - 0.25,
        tip_chord=tip_chord,
        tip_station=float(wing_z),
        inner_station=e.z_axis + 0.6 * e.radius,
        offset=e.y,
        thickness=(0.45 / root_chord, 0.45 / tip_chord),
        vertical=True,
        n_span=4,
    )
    vertices, faces, *_ = _surface(p)
    # painted like the nacelle, or white where the nacelle wears the accent colour
    rgb = g.livery.crown if g.livery.nacelle == g.livery.accent else g.livery.nacelle
    return _Part(vertices, faces, _rgba(rgb, len(faces)))


# nacelle ------------------------------------------------------------------------------


def _nacelle(e: EngineParams, livery: Livery) -> _Part:
    xf, L, Rm, Rl = e.x_front, e.length, e.radius, e.lip_radius
    r_in = 0.86 * Rl
    # (x, r, colour) along the profile, from the spinner tip to the plug tip
    profile = [
        (xf - 0.30, 0.0, livery.metal),
        (xf - 0.45, 0.18 * Rm, livery.metal),
        (xf - 0.60, 0.30 * Rm, livery.intake),  # fan face
        (xf - 0.60, r_in, livery.intake),  # intake wall
        (xf - 0.08, r_in, livery.metal),  # lip
        (xf - 0.01, r_in + 0.30 * (Rl - r_in), livery.metal),
        (xf, r_in + 0.55 * (Rl - r_in), livery.metal),
        (xf - 0.02, r_in + 0.85 * (Rl - r_in), livery.metal),
        (xf - 0.10, Rl, livery.metal),
        (xf - 0.35, Rl + 0.5 * (Rm - Rl), livery.nacelle),  # cowl
        (xf - 0.30 * L, Rm, livery.nacelle),
        (xf - 0.60 * L, Rm, livery.nacelle),
        (xf - 0.85 * L, 0.90 * Rm, livery.nacelle),
        (xf - L, 0.80 * Rm, livery.intake),  # fan nozzle
        (xf - L, 0.60 * Rm, livery.belly),  # core cowl
        (xf - L - 0.6, 0.52 * Rm, livery.intake),
        (xf - L - 0.6, 0.35 * Rm, livery.belly),  # plug
        (xf - L - 1.4, 0.0, livery.belly),
    ]
    px = np.array([p[0] for p in profile])
    pr = np.array([p[1] for p in profile])
    n = e.n_around
    phi = (np.arange(n) + 0.5) * 2 * np.pi / n
    grow = 1 / np.cos(np.pi / n)
    rings = np.stack(
        [
            np.broadcast_to(px[1:-1, None], (len(px) - 2, n)),
            e.y + pr[1:-1, None] * np.cos(phi) * grow,
            e.z_axis + pr[1:-1, None] * np.sin(phi) * grow,
        ],
        -1,
    )
    start = np.array([px[0], e.y, e.z_axis])
    end = np.array([px[-1], e.y, e.z_axis])
    vertices, faces, row, _ = _loft(rings, start, end)
    faces = _outward(vertices, faces)
    segment_rgb = np.array([p[2] for p in profile[:-1]], dtype=np.uint8)
    segment = np.clip(row + 1, 0, len(profile) - 2)  # profile segment of each face
    colors = np.concatenate([segment_rgb[segment], np.full((len(faces), 1), 255, np.uint8)], 1)
    return _Part(vertices, faces, colors)


# ----------------------------------------------------------------------------- keypoints


def _keypoint_anchors(g: AirplaneGeometry) -> dict[str, tuple[float, float, str]]:
    """(x, y, part hit first from above) of each keypoint, from the parametric geometry."""
    f, w, e, hs, fin = g.fuselage, g.wing, g.engine, g.stabiliser, g.fin
    left = {
        "wing_root_leading": (w.root_le - _INSET, w.root_station, "wing"),
        "wing_root_trailing": (w.root_le - w.root_chord + _INSET, w.root_station, "wing"),
        "wing_tip_leading": (w.tip_le - _INSET, w.tip_station - _INSET, "wing"),
        "wing_tip_trailing": (w.tip_le - w.tip_chord + _INSET, w.tip_station - _INSET, "wing"),
        "engine_front": (e.x_front - _INSET, e.y, "nacelle"),
        "stabiliser_root": (hs.root_le - _INSET, hs.root_station, "stabiliser"),
        "stabiliser_tip": (hs.tip_le - _INSET, hs.tip_station - _INSET, "stabiliser"),
    }
    anchors = {
        "nose": (f.x_nose - _INSET, 0.0, "fuselage"),
        "cockpit": (f.x_cockpit, 0.0, "fuselage"),
        "fuselage_front": (f.kp_offset, 0.0, "fuselage"),
        "fuselage_mid": (0.0, 0.0, "fuselage"),
        "fuselage_rear": (-f.kp_offset, 0.0, "fuselage"),
        "tail_end": (f.x_tail + _INSET, 0.0, "fuselage"),
        "fin_root": (fin.root_le - g.fin_root_kp_dx, 0.0, "fin"),
        "fin_tip_leading": (fin.tip_le - _INSET, 0.0, "fin"),
        "fin_tip_trailing": (fin.tip_le - fin.tip_chord + _INSET, 0.0, "fin"),
    }
    for name, (x, y, part) in left.items():
        anchors["left_" + name] = (x, y, part + "_left")
        anchors["right_" + name] = (x, -y, part + "_right")
    return anchors


def _drop_onto(mesh: trimesh.Trimesh, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of vertical rays cast down at ``xy`` (N, 2): z (N,), triangle (N,) or −1."""
    origins = np.column_stack([xy, np.full(len(xy), mesh.bounds[1, 2] + 1.0)])
    directions = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    # the numpy ray tracer (not Embree's float32 one) keeps keypoints reproducible
    tracer = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    tri, ray, loc = tracer.intersects_id(
        origins, directions, multiple_hits=True, return_locations=True
    )
    z = np.full(len(xy), -np.inf)
    first = np.full(len(xy), -1)
    for t, r, p in zip(tri, ray, loc):
        if p[2] > z[r]:
            z[r], first[r] = p[2], t
    return z, first


# ------------------------------------------------------------------------------ airplane


@dataclass(frozen=True, eq=False)
class Airplane:
    """An airplane mesh with its keypoints, in the object frame, metres.

    Attributes
    ----------
    name : str
    mesh : trimesh.Trimesh
        Triangle mesh with per-face RGBA colours (``mesh.visual.face_colors``).
    keypoints : ndarray, shape (23, 3)
        float64, in ``data_gen.keypoints.KEYPOINT_NAMES`` order, on the surface
        seen from directly above.
    keypoint_names : tuple of str
    ground_z : float
        Height of the ground plane the airplane stands on.
    part_ids : ndarray, shape (F,), optional
        Index into :data:`PART_NAMES` for each face (built airplanes only).
    """

    name: str
    mesh: trimesh.Trimesh
    keypoints: np.ndarray
    keypoint_names: tuple[str, ...]
    ground_z: float
    part_ids: np.ndarray | None = field(default=None)


def airplane_from_geometry(geometry: AirplaneGeometry, name: str = "custom") -> Airplane:
    """Build the coloured mesh of ``geometry`` and compute its keypoints.

    Parameters
    ----------
    geometry : AirplaneGeometry
    name : str

    Returns
    -------
    Airplane

    Raises
    ------
    ValueError
        If a keypoint's downward ray does not first hit the part the keypoint belongs
        to (the geometry hides it, e.g. a stabiliser root buried in the fuselage).
    """
    g = geometry
    if g.fuselage.n_around % 4 or g.engine.n_around % 4:
        raise ValueError("geometry: expected n_around of fuselage and engine divisible by 4")
    wing = _wing(g.wing, g.livery)
    nacelle = _nacelle(g.engine, g.livery)
    pylon = _pylon(g)
    stabiliser = _stabiliser(g.stabiliser, g.livery)
    parts = {
        "fuselage": _fuselage(g.fuselage, g.livery),
        "wing_left": wing,
        "wing_right": wing.mirrored(),
        "nacelle_left": nacelle,
        "nacelle_right": nacelle.mirrored(),
        "pylon_left": pylon,
        "pylon_right": pylon.mirrored(),
        "stabiliser_left": stabiliser,
        "stabiliser_right": stabiliser.mirrored(),
        "fin": _fin(g.fin, g.livery),
    }
    meshes = [
        trimesh.Trimesh(
            parts[n].vertices, parts[n].faces, face_colors=parts[n].colors, process=False
        )
        for n in PART_NAMES
    ]
    mesh = trimesh.util.concatenate(meshes)
    part_ids = np.repeat(np.arange(len(PART_NAMES)), [len(m.faces) for m in meshes])

    anchors = _keypoint_anchors(g)
    xy = np.array([anchors[n][:2] for n in KEYPOINT_NAMES], dtype=np.float64)
    z, tri = _drop_onto(mesh, xy)
    for i, n in enumerate(KEYPOINT_NAMES):
        hit = PART_NAMES[part_ids[tri[i]]] if tri[i] >= 0 else "nothing"
        if hit != anchors[n][2]:
            raise ValueError(
                f"geometry: keypoint '{n}' at (x, y) = {tuple(xy[i])} is meant to lie on "
                f"'{anchors[n][2]}' but the surface seen from above there is {hit!r}"
            )
    keypoints = np.column_stack([xy, z])
    keypoints.setflags(write=False)
    ground_z = -g.fuselage.radius - g.gear_height
    return Airplane(name, mesh, keypoints, KEYPOINT_NAMES, float(ground_z), part_ids)


def build_airplane(variant: str = "airliner") -> Airplane:
    """The mesh and keypoints of a built-in airplane variant.

    Parameters
    ----------
    variant : str
        One of ``VARIANTS``; ``'airliner'`` is the study's default, whose keypoints
        are :func:`data_gen.keypoints.airliner_keypoints`.

    Returns
    -------
    Airplane

    Examples
    --------
    >>> plane = build_airplane("airliner")
    >>> plane.keypoints.shape
    (23, 3)
    """
    if variant not in GEOMETRIES:
        raise ValueError(
            f"variant: unknown airplane variant {variant!r}; expected one of {VARIANTS}"
        )
    return airplane_from_geometry(GEOMETRIES[variant], variant)


# -------------------------------------------------------------------------- load / save


def _colored(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` with per-face colours: its own (texture, vertex or face) or light grey."""
    visual = mesh.visual
    if visual.kind is None:
        colors = np.tile(np.array(DEFAULT_RGBA, dtype=np.uint8), (len(mesh.faces), 1))
    else:
        if visual.kind == "texture":
            visual = visual.to_color()
            visual.mesh = mesh
        colors = np.asarray(visual.face_colors, dtype=np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=colors)
    return mesh


def load_airplane(mesh_path, keypoints_json) -> Airplane:
    """A user's airplane: a mesh file (OBJ, GLB, PLY, …) and its keypoint JSON.

    The JSON reads ``{"units": "m", "ground_z": -3.5, "keypoints": [{"name": "nose",
    "xyz": [x, y, z]}, …]}`` with each of the 23 keypoint names exactly once (any order),
    in the object frame (x forward, y left, z up, metres). ``ground_z`` defaults to the
    mesh's lowest point and ``name`` (optional) to the mesh file's stem. A scene is
    merged into one mesh; a mesh without colours is painted light grey.

    Parameters
    ----------
    mesh_path : str or Path
    keypoints_json : str or Path

    Returns
    -------
    Airplane
        Keypoints in ``data_gen.keypoints.KEYPOINT_NAMES`` order; ``part_ids`` None.

    Raises
    ------
    FileNotFoundError
        A file does not exist.
    ValueError
        The mesh cannot be loaded, is empty or flat (no convex hull with volume), or the
        keypoints are malformed (missing, extra or duplicate names, coordinates that are
        not three finite numbers, a keypoint farther than ``MAX_KEYPOINT_DISTANCE`` from
        the surface, keypoints that do not span the airplane or are collinear seen from
        above, a ``ground_z`` away from the mesh's lowest point).
    """
    mesh_path, keypoints_json = Path(mesh_path), Path(keypoints_json)
    for arg, path in (("mesh_path", mesh_path), ("keypoints_json", keypoints_json)):
        if not path.is_file():
            raise FileNotFoundError(f"{arg}: no such file '{path}'")
    try:
        mesh = trimesh.load(mesh_path, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"mesh_path: cannot load a mesh from '{mesh_path}': {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"mesh_path: expected a triangle mesh with faces in '{mesh_path}'")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"mesh_path: expected finite vertex coordinates in '{mesh_path}'")
    _check_solid(mesh, mesh_path)
    mesh = _colored(mesh)

    name, keypoints, ground_z = _read_keypoints(keypoints_json)
    _, distance, _ = trimesh.proximity.closest_point(mesh, keypoints)
    far = np.flatnonzero(distance > MAX_KEYPOINT_DISTANCE)
    if len(far):
        listing = ", ".join(f"{KEYPOINT_NAMES[i]} ({distance[i]:.2f} m)" for i in far)
        raise ValueError(
            f"keypoints_json: expected keypoints within {MAX_KEYPOINT_DISTANCE} m of the "
            f"surface of '{mesh_path}', got {listing}"
        )
    _check_keypoint_extent(keypoints, mesh, keypoints_json)
    if ground_z is None:
        ground_z = float(mesh.bounds[0, 2])
    _check_ground(ground_z, mesh, keypoints_json)
    keypoints.setflags(write=False)
    return Airplane(name or mesh_path.stem, mesh, keypoints, KEYPOINT_NAMES, ground_z)


def _check_keypoint_extent(keypoints: np.ndarray, mesh: trimesh.Trimesh, path: Path) -> None:
    """A ValueError unless the keypoints (23, 3) span the airplane: their extent at least
    ``MIN_KEYPOINT_SPAN`` of the mesh's, and not collinear seen from above."""
    span = float(np.ptp(keypoints, axis=0).max())
    size = float(np.ptp(mesh.vertices, axis=0).max())
    if not span >= MIN_KEYPOINT_SPAN * size:
        raise ValueError(
            f"keypoints_json: expected keypoints that span the airplane (an extent of at "
            f"least {MIN_KEYPOINT_SPAN:.0%} of the mesh's {size:.3g} m), got {span:.3g} m "
            f"in '{path}'"
        )
    xy = keypoints[:, :2] - keypoints[:, :2].mean(0)
    s = np.linalg.svd(xy, compute_uv=False)
    if not s[1] > MIN_KEYPOINT_SPREAD_RATIO * s[0]:
        raise ValueError(
            f"keypoints_json: expected keypoints that are not collinear seen from above "
            f"(x, y spread ratio {s[1] / s[0]:.2g} <= {MIN_KEYPOINT_SPREAD_RATIO}) in '{path}'"
        )


def _check_ground(ground_z: float, mesh: trimesh.Trimesh, path: Path) -> None:
    """A ValueError unless the ground plane ``z = ground_z`` touches the mesh from below:
    at most ``MAX_KEYPOINT_DISTANCE`` above its lowest point (the airplane would sink into
    it) and at most the mesh's height (or a tenth of its size) below it (it would float;
    the cameras aim at the ground, so the airplane leaves the picture)."""
    lowest = float(mesh.bounds[0, 2])
    extent = np.ptp(mesh.vertices, axis=0)
    gap = lowest - ground_z
    most = max(float(extent[2]), 0.1 * float(extent.max()))
    if not -MAX_KEYPOINT_DISTANCE <= gap <= most:
        raise ValueError(
            f"keypoints_json: expected 'ground_z' between {lowest - most:.4g} and "
            f"{lowest + MAX_KEYPOINT_DISTANCE:.4g} m (the mesh's lowest point is at "
            f"z = {lowest:.4g} m), got {ground_z:.4g} in '{path}'"
        )


def _check_solid(mesh: trimesh.Trimesh, mesh_path: Path) -> None:
    """A ValueError naming ``mesh_path`` unless the mesh spans three dimensions: the scene
    sampler frames the airplane by its convex hull, which a flat or single-triangle mesh
    (every vertex in one plane) does not have."""
    try:
        volume = float(mesh.convex_hull.volume)
    except Exception:  # scipy's QhullError for coplanar or too few points
        volume = 0.0
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    if not volume > 1e-9 * extent**3:
        raise ValueError(
            f"mesh_path: expected a mesh that spans three dimensions (a convex hull with "
            f"volume), but the {len(mesh.vertices)} vertices of '{mesh_path}' lie in a plane"
        )


def _read_keypoints(path: Path) -> tuple[str | None, np.ndarray, float | None]:
    """Name, keypoints (23, 3) in KEYPOINT_NAMES order and ground_z from a keypoint JSON."""
    arg = "keypoints_json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{arg}: '{path}' is not valid JSON: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("keypoints"), list):
        raise ValueError(f"{arg}: expected an object with a 'keypoints' list in '{path}'")
    if data.get("units", "m") != "m":
        raise ValueError(f"{arg}: expected units 'm', got {data['units']!r} in '{path}'")
    ground_z = data.get("ground_z")
    if ground_z is not None and not (_is_number(ground_z) and math.isfinite(ground_z)):
        raise ValueError(f"{arg}: expected a finite number for 'ground_z', got {ground_z!r}")
    name = data.get("name")
    if name is not None and not isinstance(name, str):
        raise ValueError(f"{arg}: expected a string for 'name', got {name!r}")

    entries: dict[str, list] = {}
    for entry in data["keypoints"]:
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise ValueError(
                f"{arg}: expected entries {{'name': str, 'xyz': [x, y, z]}}, got {entry!r}"
            )
        if entry["name"] in entries:
            raise ValueError(f"{arg}: duplicate keypoint name {entry['name']!r} in '{path}'")
        entries[entry["name"]] = entry.get("xyz")
    missing = [n for n in KEYPOINT_NAMES if n not in entries]
    extra = sorted(set(entries) - set(KEYPOINT_NAMES))
    if missing or extra:
        raise ValueError(
            f"{arg}: expected exactly the {len(KEYPOINT_NAMES)} keypoint names of "
            f"data_gen.keypoints.KEYPOINT_NAMES; missing {missing}, unknown {extra}"
        )
    rows = []
    for n in KEYPOINT_NAMES:
        xyz = entries[n]
        if not (isinstance(xyz, list) and len(xyz) == 3 and all(map(_is_number, xyz))):
            raise ValueError(f"{arg}: keypoint {n!r}: expected 'xyz' as [x, y, z], got {xyz!r}")
        if not all(math.isfinite(v) for v in xyz):
            raise ValueError(f"{arg}: keypoint {n!r}: expected finite coordinates, got {xyz}")
        rows.append(xyz)
    return name, np.array(rows, dtype=np.float64), ground_z


def _is_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def save_airplane(airplane: Airplane, directory) -> tuple[Path, Path]:
    """Write ``airplane`` as ``<name>.ply`` (face colours) and ``<name>.json`` (keypoints).

    The files are written atomically and read back by :func:`load_airplane`.

    Parameters
    ----------
    airplane : Airplane
    directory : str or Path
        Created if missing.

    Returns
    -------
    mesh_path, json_path : Path
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    mesh_path = directory / f"{airplane.name}.ply"
    json_path = directory / f"{airplane.name}.json"
    document = {
        "name": airplane.name,
        "units": "m",
        "ground_z": float(airplane.ground_z),
        "keypoints": [
            {"name": n, "xyz": [float(v) for v in p]}
            for n, p in zip(airplane.keypoint_names, airplane.keypoints)
        ],
    }
    write_bytes_atomic(mesh_path, airplane.mesh.export(file_type="ply"))
    write_text_atomic(json_path, json.dumps(document, indent=1) + "\n")
    return mesh_path, json_path
