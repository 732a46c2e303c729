"""data_gen.occluders: the occluder library's assets."""

import numpy as np
import pytest

from data_gen.occluders import FAMILIES, OCCLUDER_NAMES, Occluder, build_occluder, occluder_catalog

MIN_PER_FAMILY = {"vehicle": 18, "person": 12, "equipment": 12}


@pytest.fixture(scope="module")
def catalog():
    return occluder_catalog()


def test_library_holds_enough_distinct_named_assets_per_family(catalog):
    assert len(OCCLUDER_NAMES) >= 40 and len(set(OCCLUDER_NAMES)) == len(OCCLUDER_NAMES)
    assert [o.name for o in catalog] == list(OCCLUDER_NAMES)
    for family, minimum in MIN_PER_FAMILY.items():
        members = occluder_catalog(family)
        assert len(members) >= minimum, family
        assert all(o.family == family for o in members)
    assert {o.family for o in catalog} == set(FAMILIES)
    assert all(o.name.isidentifier() and o.name == o.name.lower() for o in catalog)


def test_every_asset_stands_on_the_ground_centred_and_coloured(catalog):
    for occ in catalog:
        mesh = occ.mesh
        assert isinstance(occ, Occluder) and len(mesh.faces) > 0, occ.name
        assert np.isfinite(mesh.vertices).all(), occ.name
        lo, hi = mesh.bounds
        assert abs(lo[2]) < 1e-6, occ.name
        np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-6, err_msg=occ.name)
        assert mesh.visual.kind == "face", occ.name
        colors = mesh.visual.face_colors
        assert colors.shape == (len(mesh.faces), 4) and colors.dtype == np.uint8, occ.name
        assert len(np.unique(colors, axis=0)) >= 2, occ.name
        assert mesh.area > 0 and (mesh.extents > 0).all(), occ.name


def test_sizes_are_plausible_per_family(catalog):
    for occ in catalog:
        length, width, height = occ.mesh.extents
        if occ.family == "person":
            assert 1.4 <= height <= 2.0, (occ.name, height)
            assert max(length, width) < 1.2, (occ.name, length, width)
        elif occ.family == "vehicle":
            assert 3.0 <= max(length, width) <= 15.0, (occ.name, length, width)
            assert length >= width, occ.name  # vehicles run along x
        else:
            assert max(length, width) <= 8.0, (occ.name, length, width)


def test_reference_dimensions():
    def extents(name):
        return build_occluder(name).mesh.extents

    assert 4.3 <= extents("ops_car_white")[0] <= 4.8
    assert 12.0 <= extents("apron_bus_blue")[0] <= 14.0
    assert 9.0 <= extents("fuel_truck_white")[0] <= 11.0
    assert 0.5 <= extents("traffic_cone")[2] <= 0.8
    ld3 = extents("uld_ld3")
    assert 1.95 <= ld3[0] <= 2.05 and 1.5 <= ld3[1] <= 1.6 and 1.6 <= ld3[2] <= 1.7


def test_building_twice_gives_identical_meshes(catalog):
    for occ in catalog:
        again = build_occluder(occ.name).mesh
        np.testing.assert_array_equal(again.vertices, occ.mesh.vertices, err_msg=occ.name)
        np.testing.assert_array_equal(again.faces, occ.mesh.faces, err_msg=occ.name)
        np.testing.assert_array_equal(again.visual.face_colors, occ.mesh.visual.face_colors)


def test_bad_name_or_family_raises_naming_the_argument():
    with pytest.raises(ValueError, match=r"^name: unknown occluder 'submarine'; expected one of "):
        build_occluder("submarine")
    with pytest.raises(ValueError, match="family"):
        occluder_catalog("aircraft")
