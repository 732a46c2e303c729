"""The rasteriser: exact pixel convention, depth, ids, shadows and shadow catchers."""

import numpy as np
import pytest
import trimesh
from matplotlib.path import Path as PolygonPath

from data_gen.camera import intrinsics
from data_gen.render import Camera, Item, Light, look_at
from kpstudy.pose.geometry import project
from tests.helpers.meshes import colored


def _ground(renderer, side=400.0):
    ground = trimesh.creation.box((side, side, 0.02))
    ground.apply_translation((0, 0, -0.01))
    return renderer.upload(colored(ground, (128, 128, 128)))


def test_projection_matches_opencv_pixel_convention(renderer):
    """A pixel is drawn iff its centre (integers, docs/design.md §3) lies in the projected quad."""
    quad = colored(trimesh.creation.box((9.0, 5.0, 0.01)), (200, 50, 50))
    quad.apply_translation((1.3, -0.7, 0.0))
    K = intrinsics(96, 64, 40.0)
    R, t = look_at((8.0, -12.0, 30.0), (0.5, 0.2, 0.0))
    frame = renderer.render(
        [Item(renderer.upload(quad), object_id=3)],
        Camera(K, R, t, 96, 64),
        Light(np.array([0, 0, 1.0])),
    )
    top = quad.vertices[quad.vertices[:, 2] > 0]
    corners = project(top, R, t, K)
    polygon = PolygonPath(corners[_order(corners)])
    rows, cols = np.mgrid[0:64, 0:96]
    centres = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    inside = polygon.contains_points(centres, radius=-0.02).reshape(64, 96)
    outside = ~polygon.contains_points(centres, radius=0.02).reshape(64, 96)
    drawn = frame.ids == 3
    assert inside.sum() > 200
    assert np.all(drawn[inside]) and not np.any(drawn[outside])


def _order(points):
    centre = points.mean(0)
    return np.argsort(np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0]))


def test_depth_is_camera_z_of_the_surface(renderer):
    K = intrinsics(80, 60, 50.0)
    R, t = look_at((5.0, 3.0, 40.0), (0.0, 0.0, 0.0))
    frame = renderer.render(
        [Item(_ground(renderer), object_id=0)],
        Camera(K, R, t, 80, 60),
        Light(np.array([0.3, 0, 1.0])),
    )
    rows, cols = np.mgrid[0:60, 0:80]
    rays = np.linalg.solve(
        K, np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)])
    )  # camera frame, z = 1
    normal = R[:, 2]
    z = (normal @ t) / (normal @ rays)  # ground plane z = 0: n·x_c = n·t
    assert np.all(frame.ids == 0)
    np.testing.assert_allclose(frame.depth.ravel(), z, rtol=2e-4)


def test_lighting_and_shadow_catcher_alpha(renderer):
    light = Light(
        np.array([0.0, 0.0, 1.0]), sun=0.8, ambient=0.3, sun_color=(1, 1, 1), sky_color=(1, 1, 1)
    )
    block = colored(trimesh.creation.box((6.0, 6.0, 4.0)), (90, 90, 90))
    block.apply_translation((0, 0, 2.0))
    K = intrinsics(64, 64, 60.0)
    R, t = look_at((0.0, 0.0, 60.0), (0.0, 0.0, 0.0))
    frame = renderer.render(
        [Item(_ground(renderer), casts_shadow=False)], Camera(K, R, t, 64, 64), light
    )
    assert frame.color[32, 32, 0] == pytest.approx(
        128 * (0.3 + 0.8), abs=2
    )  # albedo × (ambient + sun)
    catcher = renderer.upload(colored(trimesh.creation.box((100.0, 100.0, 0.02)), (0, 0, 0)))
    frame = renderer.render(
        [Item(catcher, mode="catcher", object_id=5), Item(renderer.upload(block), object_id=1)],
        Camera(K, R, t, 64, 64),
        Light(np.array([1.0, 0.0, 1.0]), sun=0.8, ambient=0.3),
        shadow_extent=40.0,
    )
    # Sun at 45° towards +x: the shadow falls on −x; its alpha is the light removed.
    shadow_uv = np.rint(project(np.array([[-5.0, 0.0, 0.0]]), R, t, K)[0]).astype(int)
    sunny_uv = np.rint(project(np.array([[8.0, 6.0, 0.0]]), R, t, K)[0]).astype(int)
    expected = 1 - 0.3 / (0.3 + 0.8 * np.cos(np.pi / 4))
    assert frame.alpha[shadow_uv[1], shadow_uv[0]] == pytest.approx(expected, abs=0.02)
    assert frame.alpha[sunny_uv[1], sunny_uv[0]] == 0.0
    assert frame.ids[sunny_uv[1], sunny_uv[0]] == -1


def test_render_is_deterministic(renderer):
    K = intrinsics(64, 48, 50.0)
    R, t = look_at((10.0, -5.0, 50.0), (0.0, 0.0, 0.0))
    box = renderer.upload(colored(trimesh.creation.box((8.0, 3.0, 3.0)), (30, 120, 200)))
    items = [Item(_ground(renderer)), Item(box, object_id=1, specular=0.4)]
    a = renderer.render(items, Camera(K, R, t, 64, 48), Light(np.array([0.4, 0.2, 1.0])))
    b = renderer.render(items, Camera(K, R, t, 64, 48), Light(np.array([0.4, 0.2, 1.0])))
    assert a.color.tobytes() == b.color.tobytes() and np.array_equal(a.depth, b.depth)


def test_bad_item_mode_and_empty_mesh(renderer):
    K = intrinsics(32, 32, 50.0)
    R, t = look_at((0.0, 0.0, 20.0), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="items: unknown mode"):
        renderer.render(
            [Item(_ground(renderer), mode="glow")],
            Camera(K, R, t, 32, 32),
            Light(np.array([0, 0, 1.0])),
        )
    with pytest.raises(ValueError, match="mesh: expected a mesh with at least one face"):
        renderer.upload(trimesh.Trimesh())
