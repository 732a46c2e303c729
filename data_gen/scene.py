"""An airplane parked on an apron, seen from above: random scene parameters and their render.

The world frame is the airplane's object frame (x to the nose, y to the left wing,
z up, metres); the ground is the plane ``z = airplane.ground_z``. A scene draws:

- the camera: heading of the image about the vertical, tilt from the nadir (≤ 20° by
  default), altitude chosen so that the airplane's projection spans a drawn fraction
  (30–70 %) of the frame, and an aim point that keeps the whole airplane in view;
- the sun (azimuth, elevation 25–75°, intensity) and the sky's ambient light;
- the ground: one of a few procedural asphalt textures, shifted and turned, with
  painted stand markings (lead-in line, stop bar, stand safety line, taxi lane,
  service road) around the airplane.

:class:`SceneParams` holds every drawn number (JSON-able, stored in the annotations),
so a scene can be rendered again, e.g. to light an occluder patch like its image.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from data_gen.render import Camera, Frame, Item, Light, Renderer, look_at

if TYPE_CHECKING:
    from data_gen.airplane import Airplane

#: Object ids in the id image.
GROUND_ID, MARKING_ID, AIRPLANE_ID = 0, 1, 2

ASPHALT_RGB = (104, 104, 108)
DETAIL_TILE_M, LARGE_TILE_M = 3.0, 90.0


@dataclass(frozen=True)
class SceneParams:
    """Everything random about one image (angles in degrees, lengths in metres)."""

    heading: float
    tilt: float
    tilt_direction: float
    coverage: float
    altitude: float
    aim: tuple[float, float]
    sun_azimuth: float
    sun_elevation: float
    sun: float
    ambient: float
    texture: int
    ground_angle: float
    ground_shift: tuple[float, float]
    markings_seed: int

    def light(self) -> Light:
        az, el = np.deg2rad(self.sun_azimuth), np.deg2rad(self.sun_elevation)
        direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return Light(direction=direction, sun=self.sun, ambient=self.ambient)

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def camera_pose(params: SceneParams, ground_z: float) -> tuple[np.ndarray, np.ndarray]:
    """Object → camera pose ``(R (3, 3), t (3,))`` of a scene's camera."""
    return _pose(
        params.heading, params.tilt, params.tilt_direction, params.altitude, params.aim, ground_z
    )


def _pose(heading, tilt, tilt_direction, altitude, aim, ground_z, **_):
    """A camera ``altitude`` metres above the ground aiming at ``aim`` (x, y), its optical
    axis ``tilt`` degrees from the nadir towards ``tilt_direction``, the image turned by
    ``heading`` about the vertical."""
    tilt, direction = np.deg2rad(tilt), np.deg2rad(tilt_direction)
    axis = np.array(
        [np.sin(tilt) * np.cos(direction), np.sin(tilt) * np.sin(direction), -np.cos(tilt)]
    )
    target = np.array([*aim, ground_z])
    eye = target - axis * altitude / np.cos(tilt)
    heading = np.deg2rad(heading)
    return look_at(eye, target, up=(np.cos(heading), np.sin(heading), 0.0))


def _span(points: np.ndarray, R, t, K) -> tuple[np.ndarray, np.ndarray]:
    """Pixel bounding box (lo (2,), hi (2,)) of points (N, 3) in front of the camera."""
    x = points @ R.T + t
    uv = x[:, :2] / x[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    return uv.min(0), uv.max(0)


def sample_scene(
    airplane: Airplane,
    K: np.ndarray,
    width: int,
    height: int,
    rng: np.random.Generator,
    *,
    coverage: tuple[float, float] = (0.3, 0.7),
    tilt_max: float = 20.0,
    n_textures: int = 4,
) -> SceneParams:
    """Draw one scene whose airplane lies wholly inside the frame.

    ``coverage`` bounds the larger of the airplane's projected bounding-box width and
    height as a fraction of the image's width and height.
    """
    hull = airplane.mesh.convex_hull.vertices
    size = np.array([width, height], float)
    margin = 0.02 * size
    for _ in range(100):
        params = dict(
            heading=rng.uniform(-180, 180),
            tilt=tilt_max * np.sqrt(rng.uniform()),
            tilt_direction=rng.uniform(0, 360),
            coverage=rng.uniform(*coverage),
            altitude=100.0,
            aim=(0.0, 0.0),
        )
        # The span scales as 1/altitude; two fixed-point steps absorb the tilt.
        for _ in range(2):
            R, t = _pose(**params, ground_z=airplane.ground_z)
            lo, hi = _span(hull, R, t, K)
            params["altitude"] *= np.max((hi - lo) / size) / params["coverage"]
        R, t = _pose(**params, ground_z=airplane.ground_z)
        lo, hi = _span(hull, R, t, K)
        slack = (size - 2 * margin - (hi - lo)) / 2
        if np.any(slack <= 0):
            continue
        # Shift the image by up to the slack: move the aim point on the ground.
        shift_px = rng.uniform(-1, 1, 2) * slack - ((lo + hi) / 2 - K[:2, 2])
        metres_per_px = params["altitude"] / K[0, 0]
        params["aim"] = tuple(float(x) for x in -(R[:2, :2].T @ shift_px) * metres_per_px)
        scene = SceneParams(
            **params,
            sun_azimuth=rng.uniform(0, 360),
            sun_elevation=rng.uniform(25, 75),
            sun=rng.uniform(0.55, 0.95),
            ambient=rng.uniform(0.25, 0.45),
            texture=int(rng.integers(n_textures)),
            ground_angle=rng.uniform(0, 360),
            ground_shift=tuple(float(x) for x in rng.uniform(0, LARGE_TILE_M, 2)),
            markings_seed=int(rng.integers(2**31)),
        )
        R, t = camera_pose(scene, airplane.ground_z)
        lo, hi = _span(hull, R, t, K)
        if np.all(lo >= margin - 0.5) and np.all(hi <= size - margin - 0.5):
            return scene
    raise RuntimeError("sample_scene: could not fit the airplane in the frame in 100 draws")


def _periodic_noise(rng: np.random.Generator, size: int, exponent: float, low_cut: float = 1.0):
    """Tileable noise (size, size) with power spectrum ∝ f^−exponent, zero mean, unit std."""
    f = np.fft.fftfreq(size) * size
    radius = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    amplitude = np.where(radius >= low_cut, np.maximum(radius, 1.0) ** (-exponent / 2), 0.0)
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) * amplitude
    noise = np.fft.ifft2(spectrum).real
    return (noise - noise.mean()) / (noise.std() + 1e-12)


def asphalt_textures(
    seed: int, count: int = 4, size: int = 512
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` pairs of tileable asphalt textures (detail, large), each (size, size, 3) uint8.

    Detail (one tile = ``DETAIL_TILE_M`` metres): grain and light aggregate. Large (one
    tile = ``LARGE_TILE_M`` metres): patched repairs, stains and tyre-darkened bands.
    Grey 128 is neutral: the renderer multiplies them into the asphalt colour.
    """
    rng = np.random.default_rng(seed)
    textures = []
    for _ in range(count):
        grain = 0.6 * _periodic_noise(rng, size, 1.2) + 0.4 * rng.standard_normal((size, size))
        aggregate = (rng.uniform(size=(size, size)) < 0.02) * rng.uniform(0.3, 0.7, (size, size))
        detail = 128 * (1 + 0.07 * grain + 0.35 * aggregate)
        warm = rng.uniform(-0.03, 0.03)
        tint = np.array([1 + warm, 1.0, 1 - warm])
        detail = detail[..., None] * tint
        smooth = _periodic_noise(rng, size, 3.2)
        patches = _periodic_noise(rng, size, 4.0, low_cut=2.0)
        repaired = np.where(patches > 1.2, rng.uniform(-0.18, 0.12), 0.0)
        stains = np.minimum(_periodic_noise(rng, size, 2.6) + 2.0, 0.0) * 0.25
        large = 128 * (1 + 0.03 * smooth + repaired + stains)
        textures.append(
            (
                np.clip(detail, 0, 255).astype(np.uint8),
                np.clip(large, 0, 255)[..., None].repeat(3, -1).astype(np.uint8),
            )
        )
    return textures


_PAINT = {
    "yellow": (232, 190, 40, 255),
    "white": (235, 235, 230, 255),
    "red": (200, 40, 35, 255),
}


def _stripes(segments: list[tuple], z: float) -> trimesh.Trimesh:
    """Painted lines as flat quads at height ``z``: one (p0, p1, width, colour) per segment."""
    p0 = np.array([s[0] for s in segments], float)
    p1 = np.array([s[1] for s in segments], float)
    half = np.array([s[2] for s in segments])[:, None] / 2
    d = p1 - p0
    side = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True) * half
    corners = np.stack([p0 - side, p1 - side, p1 + side, p0 + side], 1).reshape(-1, 2)
    vertices = np.column_stack([corners, np.full(len(corners), z)])
    base = 4 * np.arange(len(segments))[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    colors = np.array([_PAINT[s[3]] for s in segments], np.uint8)
    return trimesh.Trimesh(
        vertices, faces, face_colors=np.concatenate([colors, colors]), process=False
    )


def _polyline(points, width, color, dash: float | None = None) -> list[tuple]:
    """Segments of a (dashed) painted polyline through ``points`` (x, y)."""
    segments = []
    for p0, p1 in zip(np.asarray(points[:-1], float), np.asarray(points[1:], float)):
        if dash is None:
            segments.append((p0, p1, width, color))
            continue
        n = max(int(np.linalg.norm(p1 - p0) // (2 * dash)), 1)
        cuts = np.linspace(0, 1, 2 * n + 1)
        segments += [
            (p0 + a * (p1 - p0), p0 + b * (p1 - p0), width, color)
            for a, b in zip(cuts[0:-1:2], cuts[1::2])
        ]
    return segments


def stand_markings(airplane: Airplane, seed: int) -> trimesh.Trimesh:
    """Painted apron markings of the airplane's stand (metres, world frame, on the ground)."""
    rng = np.random.default_rng(seed)
    z = airplane.ground_z + 0.01
    (x_min, y_min, _), (x_max, y_max, _) = airplane.mesh.bounds
    offset = rng.uniform(-0.4, 0.4)
    stop = x_max + rng.uniform(1.5, 4.0)
    lane = x_min - rng.uniform(12, 20)
    side, radius = rng.choice([-1.0, 1.0]), rng.uniform(18, 30)
    # Lead-in line: from the taxi lane, a quarter circle onto the centreline, to the stop bar.
    arc = np.linspace(0, np.pi / 2, 12)
    lead = np.stack(
        [lane + radius * (1 - np.cos(arc)), offset + side * radius * (1 - np.sin(arc))], 1
    )
    parts = _polyline([*lead, (stop, offset)], 0.15, "yellow")
    parts += _polyline([(lane, y_min - 60), (lane, y_max + 60)], 0.15, "yellow")
    parts += _polyline([(stop, offset - 1.5), (stop, offset + 1.5)], 0.3, "yellow")
    # Stand safety line (red) with a margin around the airplane.
    m = rng.uniform(3, 6)
    box = [
        (x_min - m, y_min - m),
        (stop + m, y_min - m),
        (stop + m, y_max + m),
        (x_min - m, y_max + m),
        (x_min - m, y_min - m),
    ]
    parts += _polyline(box, 0.2, "red")
    # Equipment restraint line (white, dashed) and a service road beyond the stop bar.
    side = rng.choice([-1.0, 1.0])
    y_line = side * (max(y_max, -y_min) + m + rng.uniform(4, 8))
    parts += _polyline([(x_min - m, y_line), (stop + m, y_line)], 0.15, "white", dash=1.5)
    road = stop + m + rng.uniform(4, 10)
    for dx, dash in ((0.0, None), (3.5, 1.5), (7.0, None)):
        parts += _polyline(
            [(road + dx, y_min - 60), (road + dx, y_max + 60)], 0.15, "white", dash=dash
        )
    return _stripes(parts, z)


class SceneRenderer:
    """Renders scenes of one airplane: the airplane, the ground textures and the renderer
    are set up once; markings are made per image.

    Parameters
    ----------
    airplane : Airplane
    texture_seed : int
        Seed of the asphalt textures (one set per dataset).
    n_textures : int
        How many asphalt textures scenes choose from.
    """

    def __init__(self, airplane: Airplane, texture_seed: int = 0, n_textures: int = 4):
        self.airplane = airplane
        self.renderer = Renderer()
        self.airplane_gpu = self.renderer.upload(airplane.mesh)
        self.textures = [
            self.renderer.ground_textures(d, g, (DETAIL_TILE_M, LARGE_TILE_M))
            for d, g in asphalt_textures(texture_seed, n_textures)
        ]
        ground = trimesh.creation.box((2000.0, 2000.0, 0.02))
        ground.apply_translation((0, 0, -0.01))
        ground.visual.face_colors = (*ASPHALT_RGB, 255)
        self._ground = ground

    def render(
        self, params: SceneParams, K: np.ndarray, width: int, height: int
    ) -> tuple[Frame, np.ndarray, np.ndarray]:
        """Render a scene; returns the frame and the camera pose ``(R, t)``."""
        R, t = camera_pose(params, self.airplane.ground_z)
        camera = Camera(
            K, R, t, width, height, znear=0.1 * params.altitude, zfar=10 * params.altitude
        )
        textures = self.textures[params.texture % len(self.textures)]
        ground = self.renderer.upload(self._ground, textures)
        markings = self.renderer.upload(
            stand_markings(self.airplane, params.markings_seed), textures
        )
        angle = np.deg2rad(params.ground_angle)
        ground_pose = np.eye(4)
        ground_pose[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        ground_pose[:3, 3] = [*params.ground_shift, self.airplane.ground_z]
        items = [
            Item(ground, ground_pose, GROUND_ID, casts_shadow=False),
            Item(markings, np.eye(4), MARKING_ID, casts_shadow=False),
            Item(self.airplane_gpu, np.eye(4), AIRPLANE_ID, specular=0.35),
        ]
        extent = float(np.ptp(self.airplane.mesh.bounds[:, :2], axis=0).max()) * 0.5 + 30.0
        frame = self.renderer.render(
            items,
            camera,
            params.light(),
            shadow_center=(0.0, 0.0, self.airplane.ground_z),
            shadow_extent=extent,
        )
        ground.release()
        markings.release()
        return frame, R, t

    def close(self) -> None:
        self.renderer.release()


def keypoint_visibility(
    frame: Frame,
    keypoints: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    tol: float = 0.3,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (23, 2) and COCO visibility flags (23,) of keypoints (23, 3) in a frame.

    A z-buffer test at the keypoint's pixel: 2 = visible (inside the image and nothing
    drawn there is more than ``tol`` metres in front of the keypoint: the pixel shows
    the keypoint's own surface, or, at a thin edge that covers less than the pixel's
    centre, the ground behind it); 1 = inside but hidden; 0 = outside, or behind the
    camera (depth ≤ 0, whose projection is a mirror image).
    """
    x = keypoints @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = x[:, :2] / x[:, 2:] @ K[:2, :2].T + K[:2, 2]
    h, w = frame.depth.shape
    front = (x[:, 2] > 0) & np.isfinite(uv).all(1)
    col, row = (np.rint(np.where(front, c, -1)).astype(int) for c in uv.T)
    inside = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flags = np.zeros(len(keypoints), int)
    c, r = col[inside], row[inside]
    seen = frame.depth[r, c] >= x[inside, 2] - tol
    flags[inside] = np.where(seen, 2, 1)
    return uv, flags
