"""data_gen.patches: occluder patches rendered at image scale, their shadows and pasting."""

import numpy as np
import pytest
import trimesh

from data_gen.patches import PatchRenderer, paste, patch_light
from data_gen.render import Light
from tests.helpers.meshes import colored


def test_patch_scale_shadow_and_paste(renderer):
    patches = PatchRenderer(renderer)
    car = colored(trimesh.creation.box((4.0, 2.0, 1.5)), (200, 30, 30))
    car.apply_translation((0, 0, 0.75))
    # Camera looking straight down: the patch's light is the scene's, unchanged.
    light = patch_light(
        Light(np.array([0.0, 0.0, 1.0]), sun=0.8, ambient=0.3), np.diag([1.0, -1.0, -1.0])
    )
    patch = patches.render("car", car, px_per_m=10.0, light=light)
    solid = patch[..., 3] == 1.0
    rows, cols = np.nonzero(solid)
    assert np.ptp(cols) + 1 == pytest.approx(40, abs=1) and np.ptp(rows) + 1 == pytest.approx(
        20, abs=1
    )
    low_sun = patch_light(
        Light(np.array([1.0, 0.0, 0.5]), sun=0.8, ambient=0.3), np.diag([1.0, -1.0, -1.0])
    )
    shadowed = patches.render("car", car, px_per_m=10.0, light=low_sun)
    assert shadowed.shape[1] > patch.shape[1]  # the shadow stretches the patch away from the sun
    assert np.any((shadowed[..., 3] > 0.2) & (shadowed[..., 3] < 1))
    image = np.full((60, 80, 3), 100, np.uint8)
    out, alpha = paste(image, patch, (5, 7))
    h, w = patch.shape[:2]
    assert np.array_equal(out[alpha == 0], image[alpha == 0])
    np.testing.assert_allclose(
        out[7 : 7 + h, 5 : 5 + w][solid], np.rint(patch[..., :3][solid]), atol=0.5
    )
    with pytest.raises(ValueError, match="top_left"):
        paste(image, patch, (70, 7))
