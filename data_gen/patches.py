"""Occluder patches: an occluder rendered top-down to an RGBA image, lit like a scene.

The patch is seen straight down by a distant camera (near-orthographic) at a given
ground scale (pixels per metre), with the sun placed where the scene's sun is
relative to the scene's camera, so shading and the direction of the cast shadow
agree with the image it is pasted on. The occluder's shadow on the ground is part of
the patch: black with the alpha of the light it removes.
"""

from __future__ import annotations

import numpy as np
import trimesh

from data_gen.render import Camera, GpuMesh, Item, Light, Renderer

NADIR = np.diag([1.0, -1.0, -1.0])  # camera looking down: image x = world x, image y = −world y
_DISTANCE = 2000.0  # metres from the camera to the ground
OCCLUDER_ID, CATCHER_ID = 1, 2


def patch_light(light: Light, R_scene: np.ndarray) -> Light:
    """The scene's light re-expressed for the patch camera: same sun direction in the image."""
    direction = NADIR.T @ (R_scene @ np.asarray(light.direction, float))
    if direction[2] <= 0.05:  # the sun stays above the patch's ground
        direction[2] = 0.05
    return Light(
        direction / np.linalg.norm(direction),
        light.sun,
        light.ambient,
        light.sun_color,
        light.sky_color,
    )


class PatchRenderer:
    """Renders occluder meshes to RGBA patches; meshes are uploaded once and cached."""

    def __init__(self, renderer: Renderer | None = None):
        self.renderer = renderer or Renderer(shadow_size=1024)
        self._meshes: dict[str, GpuMesh] = {}
        catcher = trimesh.creation.box((200.0, 200.0, 0.02))
        catcher.apply_translation((0, 0, -0.01))
        self._catcher = self.renderer.upload(catcher)

    def render(
        self,
        name: str,
        mesh: trimesh.Trimesh,
        px_per_m: float,
        light: Light,
        yaw: float = 0.0,
        *,
        shadow: bool = True,
    ) -> np.ndarray:
        """RGBA patch (h, w, 4) float32 (colour in [0, 255], alpha in [0, 1]), cropped to
        its visible pixels.

        ``light`` is already in the patch frame (:func:`patch_light`); ``yaw`` turns the
        occluder about the vertical, degrees.
        """
        if name not in self._meshes:
            self._meshes[name] = self.renderer.upload(mesh)
        extent = float(np.linalg.norm(mesh.extents[:2]) / 2 + mesh.extents[2] * 2.5 + 0.5)
        side = int(np.ceil(2 * extent * px_per_m)) + 3
        f = px_per_m * _DISTANCE
        K = np.array([[f, 0, (side - 1) / 2], [0, f, (side - 1) / 2], [0, 0, 1]])
        camera = Camera(
            K, NADIR, np.array([0.0, 0.0, _DISTANCE]), side, side, _DISTANCE - 50, _DISTANCE + 50
        )
        pose = np.eye(4)
        a = np.deg2rad(yaw)
        pose[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        items = [Item(self._meshes[name], pose, OCCLUDER_ID)]
        if shadow:
            items.append(
                Item(self._catcher, np.eye(4), CATCHER_ID, mode="catcher", casts_shadow=False)
            )
        frame = self.renderer.render(items, camera, light, shadow_extent=extent)
        alpha = np.where(frame.ids == OCCLUDER_ID, 1.0, frame.alpha).astype(np.float32)
        alpha[alpha < 1 / 255] = 0.0
        rows, cols = np.nonzero(alpha)
        if len(rows) == 0:
            return np.zeros((0, 0, 4), np.float32)
        crop = np.s_[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
        color = np.where((frame.ids == OCCLUDER_ID)[..., None], frame.color, 0).astype(np.float32)
        return np.concatenate([color[crop], alpha[crop][..., None]], axis=-1)


def paste(
    image: np.ndarray, patch: np.ndarray, top_left: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Alpha-composite ``patch`` (h, w, 4) onto ``image`` (H, W, 3) uint8 at ``(x, y)``.

    Returns the new uint8 image and the patch's alpha on the image's grid (H, W).
    The patch must lie inside the image.
    """
    h, w = patch.shape[:2]
    x, y = top_left
    H, W = image.shape[:2]
    if not (0 <= x and 0 <= y and x + w <= W and y + h <= H):
        raise ValueError(f"top_left: a {w}x{h} patch at {top_left} leaves the {W}x{H} image")
    alpha = np.zeros((H, W), np.float32)
    alpha[y : y + h, x : x + w] = patch[..., 3]
    out = image.astype(np.float32)
    region = out[y : y + h, x : x + w]
    a = patch[..., 3:]
    out[y : y + h, x : x + w] = region * (1 - a) + patch[..., :3] * a
    return np.clip(np.rint(out), 0, 255).astype(np.uint8), alpha
