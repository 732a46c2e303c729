"""Headless OpenGL rasteriser for overhead scenes (moderngl on an EGL context).

One draw pass writes three images at once: the shaded colour (RGBA), the camera
depth ``z`` (metres along the optical axis) and an object id per pixel. Lighting is a
directional sun with shadow mapping (3×3 percentage-closer filtering), an ambient sky
term and a small specular highlight. A ``catcher`` item receives shadows only: its
alpha is the fraction of sunlight its shadow removes, so a patch rendered on a
catcher carries its own cast shadow.

Cameras are OpenCV pinhole cameras (``x_c = R p + t``, pixel centres on integers,
docs/design.md §3); the projection below maps them exactly onto OpenGL's window
coordinates, so a point projects to the same ``(u, v)`` as :func:`kpstudy.pose.geometry.project`.
Meshes are trimesh meshes with per-face colours, drawn flat-shaded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import moderngl
import numpy as np
import trimesh

_VERTEX = """
#version 330
uniform mat4 model;
uniform mat4 view;
uniform mat4 proj;
uniform mat4 light_view_proj;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
in vec2 in_uv;
out vec3 v_world;
out vec3 v_normal;
out vec3 v_color;
out vec2 v_uv;
out vec4 v_light;
out float v_z;
void main() {
    vec4 world = model * vec4(in_pos, 1.0);
    vec4 cam = view * world;
    v_world = world.xyz;
    v_normal = mat3(model) * in_normal;
    v_color = in_color;
    v_uv = in_uv;
    v_light = light_view_proj * world;
    v_z = cam.z;
    gl_Position = proj * cam;
}
"""

_FRAGMENT = """
#version 330
uniform vec3 sun_dir;
uniform vec3 sun_color;
uniform vec3 sky_color;
uniform float sun;
uniform float ambient;
uniform float specular;
uniform vec3 camera_pos;
uniform int mode;            // 0: lit surface, 1: shadow catcher
uniform float object_id;
uniform bool use_texture;
uniform vec2 texture_scale;  // metres per tile of the detail and of the large texture
uniform sampler2D detail_tex;
uniform sampler2D large_tex;
uniform sampler2DShadow shadow_map;
uniform vec2 shadow_texel;
in vec3 v_world;
in vec3 v_normal;
in vec3 v_color;
in vec2 v_uv;
in vec4 v_light;
in float v_z;
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec2 f_depth_id;

float sunlight(vec3 n) {
    vec3 p = v_light.xyz / v_light.w * 0.5 + 0.5;
    float bias = 0.0004 + 0.0016 * (1.0 - max(dot(n, sun_dir), 0.0));
    float lit = 0.0;
    for (int i = -1; i <= 1; ++i)
        for (int j = -1; j <= 1; ++j)
            lit += texture(shadow_map, vec3(p.xy + vec2(i, j) * shadow_texel, p.z - bias));
    return lit / 9.0;
}

void main() {
    vec3 n = normalize(v_normal);
    vec3 to_camera = normalize(camera_pos - v_world);
    if (dot(n, to_camera) < 0.0) n = -n;
    float lambert = max(dot(n, sun_dir), 0.0);
    float lit = sunlight(n);
    f_depth_id = vec2(v_z, object_id);
    if (mode == 1) {
        float full = ambient + sun * lambert;
        f_color = vec4(0.0, 0.0, 0.0, 1.0 - (ambient + sun * lambert * lit) / full);
        return;
    }
    vec3 albedo = v_color;
    if (use_texture) {
        albedo *= texture(detail_tex, v_uv / texture_scale.x).rgb
                * texture(large_tex, v_uv / texture_scale.y).rgb * 4.0;
    }
    vec3 h = normalize(sun_dir + to_camera);
    float spec = specular * pow(max(dot(n, h), 0.0), 40.0) * lit * sun;
    vec3 c = albedo * (ambient * sky_color + sun * lambert * lit * sun_color) + spec * sun_color;
    f_color = vec4(clamp(c, 0.0, 1.0), 1.0);
}
"""

_SHADOW_VERTEX = """
#version 330
uniform mat4 model;
uniform mat4 light_view_proj;
in vec3 in_pos;
void main() { gl_Position = light_view_proj * model * vec4(in_pos, 1.0); }
"""

_SHADOW_FRAGMENT = """
#version 330
void main() {}
"""


@dataclass(frozen=True)
class Light:
    """Sun and sky.

    ``direction`` (3,) points from the scene towards the sun (world frame, unit
    length); ``sun`` and ``ambient`` scale the sun's and the sky's contribution.
    """

    direction: np.ndarray
    sun: float = 0.8
    ambient: float = 0.35
    sun_color: tuple[float, float, float] = (1.0, 0.97, 0.9)
    sky_color: tuple[float, float, float] = (0.92, 0.96, 1.05)

    def as_dict(self) -> dict:
        return {
            "direction": [float(x) for x in self.direction],
            "sun": float(self.sun),
            "ambient": float(self.ambient),
            "sun_color": list(self.sun_color),
            "sky_color": list(self.sky_color),
        }


@dataclass(frozen=True)
class Camera:
    """OpenCV pinhole camera: intrinsics ``K`` (3, 3), pose ``x_c = R p + t``, image size."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    znear: float = 1.0
    zfar: float = 2000.0

    @property
    def position(self) -> np.ndarray:
        """Camera centre in the world frame, (3,)."""
        return -self.R.T @ self.t

    def view(self) -> np.ndarray:
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = self.R, self.t
        return view

    def projection(self) -> np.ndarray:
        """OpenGL clip matrix of the camera frame (x right, y down, z forward).

        Window x = u + 0.5 and window y = H − (v + 0.5): pixel centres on integers.
        """
        (fx, s, cx), (_, fy, cy) = self.K[0], self.K[1]
        w, h, n, f = self.width, self.height, self.znear, self.zfar
        return np.array(
            [
                [2 * fx / w, 2 * s / w, 2 * (cx + 0.5) / w - 1, 0],
                [0, -2 * fy / h, 1 - 2 * (cy + 0.5) / h, 0],
                [0, 0, (f + n) / (f - n), -2 * f * n / (f - n)],
                [0, 0, 1, 0],
            ]
        )


@dataclass
class Item:
    """One mesh in a scene: where it is, what id its pixels get and how it is shaded.

    ``mesh`` is a :class:`GpuMesh` from :meth:`Renderer.upload`; ``pose`` (4, 4) maps
    the mesh's frame to the world; ``object_id`` ≥ 0 is written to the id image
    (0 is reserved for the ground); ``mode`` is ``'lit'`` or ``'catcher'``.
    """

    mesh: GpuMesh
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    object_id: int = 0
    mode: str = "lit"
    casts_shadow: bool = True
    specular: float = 0.0


@dataclass
class GpuMesh:
    """Vertex buffers of an uploaded mesh (flat-shaded, one colour per face)."""

    vao: moderngl.VertexArray
    shadow_vao: moderngl.VertexArray
    buffer: moderngl.Buffer
    textures: GroundTextures | None = None

    def release(self) -> None:
        """Free the vertex buffers (the textures are shared and stay)."""
        self.vao.release()
        self.shadow_vao.release()
        self.buffer.release()


@dataclass
class GroundTextures:
    """Two tiled textures multiplied into a mesh's colours (grey 128 is neutral):
    ``detail`` repeats every ``scale[0]`` metres, ``large`` every ``scale[1]``."""

    detail: moderngl.Texture
    large: moderngl.Texture
    scale: tuple[float, float]


@dataclass(frozen=True)
class Frame:
    """A rendered image: ``color`` (H, W, 3) uint8, ``alpha`` (H, W) float32 in [0, 1],
    ``depth`` (H, W) float32 camera z in metres (0 where nothing was drawn), ``ids``
    (H, W) int32 object ids (−1 where nothing was drawn)."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    ids: np.ndarray


def _vertex_data(mesh: trimesh.Trimesh, uv_from_xy: bool) -> np.ndarray:
    """Per-corner vertex records (3F, 11): position, face normal, colour in [0, 1], uv."""
    corners = mesh.vertices[mesh.faces].reshape(-1, 3)
    normals = np.repeat(mesh.face_normals, 3, axis=0)
    colors = getattr(mesh.visual, "face_colors", None)
    if colors is None or len(colors) != len(mesh.faces):
        colors = np.full((len(mesh.faces), 4), 200, np.uint8)
    colors = np.repeat(np.asarray(colors)[:, :3] / 255.0, 3, axis=0)
    uv = corners[:, :2] if uv_from_xy else np.zeros((len(corners), 2))
    return np.concatenate([corners, normals, colors, uv], axis=1).astype("f4")


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``(R, t)`` of a camera at ``eye`` whose optical axis passes through ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: image x follows world x
        x = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


class Renderer:
    """An offscreen OpenGL context with the scene shader; framebuffers are made per size.

    Parameters
    ----------
    shadow_size : int
        Side of the square shadow map, texels.

    Raises
    ------
    RuntimeError
        When no headless OpenGL context can be created (the EGL and Mesa libraries
        that ``make setup`` installs are missing).
    """

    def __init__(self, shadow_size: int = 2048):
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as err:  # moderngl raises bare Exceptions for a missing EGL
            raise RuntimeError(
                "renderer: cannot create a headless OpenGL context on EGL "
                f"({err}); install libegl1 and libgl1-mesa-dri (make setup does)"
            ) from err
        self.program = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
        self.shadow_program = self.ctx.program(
            vertex_shader=_SHADOW_VERTEX, fragment_shader=_SHADOW_FRAGMENT
        )
        self.shadow_size = shadow_size
        self.shadow_map = self.ctx.depth_texture((shadow_size, shadow_size))
        self.shadow_map.compare_func = "<="
        self.shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.shadow_map.repeat_x = self.shadow_map.repeat_y = False
        self.shadow_fbo = self.ctx.framebuffer(depth_attachment=self.shadow_map)
        self._framebuffers: dict[tuple[int, int], moderngl.Framebuffer] = {}

    def release(self) -> None:
        self.ctx.release()

    def _texture(self, image: np.ndarray) -> moderngl.Texture:
        image = np.ascontiguousarray(image[::-1])  # OpenGL's first row is the bottom
        tex = self.ctx.texture(image.shape[1::-1], 3, image.tobytes())
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.anisotropy = 8.0
        return tex

    def ground_textures(
        self, detail: np.ndarray, large: np.ndarray, scale: tuple[float, float]
    ) -> GroundTextures:
        """Upload two RGB uint8 images (H, W, 3) as tiled ground textures."""
        return GroundTextures(
            self._texture(np.asarray(detail, np.uint8)),
            self._texture(np.asarray(large, np.uint8)),
            (float(scale[0]), float(scale[1])),
        )

    def upload(self, mesh: trimesh.Trimesh, textures: GroundTextures | None = None) -> GpuMesh:
        """Copy a mesh to the GPU; ``textures`` are tiled over its x-y plane."""
        if len(mesh.faces) == 0:
            raise ValueError("mesh: expected a mesh with at least one face")
        buffer = self.ctx.buffer(_vertex_data(mesh, textures is not None).tobytes())
        vao = self.ctx.vertex_array(
            self.program,
            [(buffer, "3f 3f 3f 2f", "in_pos", "in_normal", "in_color", "in_uv")],
        )
        shadow_vao = self.ctx.vertex_array(self.shadow_program, [(buffer, "3f 32x", "in_pos")])
        return GpuMesh(vao, shadow_vao, buffer, textures)

    def _framebuffer(self, width: int, height: int) -> moderngl.Framebuffer:
        key = (width, height)
        if key not in self._framebuffers:
            self._framebuffers[key] = self.ctx.framebuffer(
                color_attachments=[
                    self.ctx.renderbuffer(key, 4),
                    self.ctx.renderbuffer(key, 2, dtype="f4"),
                ],
                depth_attachment=self.ctx.depth_renderbuffer(key),
            )
        return self._framebuffers[key]

    def _light_view_proj(self, light: Light, center: np.ndarray, extent: float) -> np.ndarray:
        """Orthographic sun camera over a square of half-side ``extent`` around ``center``."""
        direction = np.asarray(light.direction, float)
        direction = direction / np.linalg.norm(direction)
        depth = 4 * extent
        R, t = look_at(center + direction * depth / 2, center)
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = R, t
        proj = np.diag([1 / extent, 1 / extent, 2 / depth, 1.0])
        proj[2, 3] = -1.0
        return proj @ view

    def render(
        self,
        items: list[Item],
        camera: Camera,
        light: Light,
        *,
        shadow_center=(0.0, 0.0, 0.0),
        shadow_extent: float = 60.0,
    ) -> Frame:
        """Draw ``items`` seen by ``camera`` under ``light``.

        Shadows are cast by items with ``casts_shadow`` inside the square of half-side
        ``shadow_extent`` metres (seen from the sun) around ``shadow_center``.
        """
        ctx = self.ctx
        light_vp = self._light_view_proj(light, np.asarray(shadow_center, float), shadow_extent)
        f4 = lambda m: np.ascontiguousarray(m.T, dtype="f4").tobytes()  # noqa: E731 column-major

        self.shadow_fbo.use()
        self.shadow_fbo.clear(depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self.shadow_program["light_view_proj"].write(f4(light_vp))
        for item in items:
            if item.casts_shadow and item.mode == "lit":
                self.shadow_program["model"].write(f4(np.asarray(item.pose, float)))
                item.mesh.shadow_vao.render()

        fbo = self._framebuffer(camera.width, camera.height)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        prog = self.program
        direction = np.asarray(light.direction, float)
        prog["sun_dir"].value = tuple(direction / np.linalg.norm(direction))
        prog["sun_color"].value = tuple(light.sun_color)
        prog["sky_color"].value = tuple(light.sky_color)
        prog["sun"].value = float(light.sun)
        prog["ambient"].value = float(light.ambient)
        prog["camera_pos"].value = tuple(camera.position)
        prog["view"].write(f4(camera.view()))
        prog["proj"].write(f4(camera.projection()))
        prog["light_view_proj"].write(f4(light_vp))
        prog["shadow_texel"].value = (1 / self.shadow_size, 1 / self.shadow_size)
        prog["shadow_map"].value = 0
        prog["detail_tex"].value = 1
        prog["large_tex"].value = 2
        self.shadow_map.use(0)
        # Opaque surfaces first, then catchers blended over them.
        for item in sorted(items, key=lambda i: i.mode == "catcher"):
            if item.mode not in ("lit", "catcher"):
                raise ValueError(f"items: unknown mode {item.mode!r}; expected 'lit' or 'catcher'")
            prog["model"].write(f4(np.asarray(item.pose, float)))
            prog["mode"].value = int(item.mode == "catcher")
            prog["object_id"].value = float(item.object_id)
            prog["specular"].value = float(item.specular)
            textures = item.mesh.textures
            prog["use_texture"].value = textures is not None
            if textures is not None:
                textures.detail.use(1)
                textures.large.use(2)
                prog["texture_scale"].value = textures.scale
            item.mesh.vao.render()

        w, h = camera.width, camera.height
        rgba = np.frombuffer(fbo.read(components=4, attachment=0), np.uint8).reshape(h, w, 4)
        depth_id = np.frombuffer(
            fbo.read(components=2, attachment=1, dtype="f4"), np.float32
        ).reshape(h, w, 2)
        rgba, depth_id = rgba[::-1], depth_id[::-1]
        drawn = rgba[..., 3] > 0
        return Frame(
            color=np.ascontiguousarray(rgba[..., :3]),
            alpha=rgba[..., 3].astype(np.float32) / 255.0,
            depth=np.where(drawn, depth_id[..., 0], 0.0).astype(np.float32),
            ids=np.where(drawn, np.rint(depth_id[..., 1]), -1).astype(np.int32),
        )
