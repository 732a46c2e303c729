"""data_gen.airplane: the variants' meshes and keypoints, saving and loading a user's
mesh and keypoint JSON, and the refusal of degenerate keypoint JSON (issue 29, point 6):
keypoints that do not span the airplane and a ground plane away from the mesh are refused
when the airplane is loaded, before anything is rendered."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh

from data_gen.airplane import (
    DEFAULT_RGBA,
    GEOMETRIES,
    PART_NAMES,
    VARIANTS,
    build_airplane,
    load_airplane,
    save_airplane,
)
from data_gen.keypoints import KEYPOINT_NAMES, airliner_keypoints

IDX = {n: i for i, n in enumerate(KEYPOINT_NAMES)}


@pytest.fixture(scope="module")
def planes():
    return {v: build_airplane(v) for v in VARIANTS}


@pytest.fixture(scope="module")
def saved(planes, tmp_path_factory):
    """The default airliner written once: (mesh_path, json_path, parsed json)."""
    mesh_path, json_path = save_airplane(planes["airliner"], tmp_path_factory.mktemp("plane"))
    return mesh_path, json_path, json.loads(json_path.read_text())


def first_hits(mesh, xy, z0=50.0):
    """z and triangle of the first surface met by rays cast straight down from z0."""
    origins = np.column_stack([xy, np.full(len(xy), z0)])
    directions = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    tri, ray, loc = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_id(
        origins, directions, multiple_hits=True, return_locations=True
    )
    z, first = np.full(len(xy), -np.inf), np.full(len(xy), -1)
    for t, r, p in zip(tri, ray, loc):
        if p[2] > z[r]:
            z[r], first[r] = p[2], t
    return z, first


@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_is_an_airliner_sized_coloured_closed_mesh(planes, variant):
    plane = planes[variant]
    mesh = plane.mesh
    assert plane.name == variant
    assert np.all(np.isfinite(mesh.vertices)) and len(mesh.faces) <= 30_000
    extent = mesh.extents
    assert 35 <= extent[0] <= 45  # length
    assert 30 <= extent[1] <= 45  # span
    colors = np.asarray(mesh.visual.face_colors)
    assert colors.shape == (len(mesh.faces), 4) and colors.dtype == np.uint8
    assert len(np.unique(colors, axis=0)) >= 6
    # it stands on the ground, gear below the fuselage
    assert -4.5 < plane.ground_z < mesh.bounds[0, 2]
    # every part is a closed, outward-facing surface (a rasteriser may cull back faces)
    assert plane.part_ids.shape == (len(mesh.faces),)
    assert set(np.unique(plane.part_ids)) == set(range(len(PART_NAMES)))
    for k, name in enumerate(PART_NAMES):
        part = mesh.submesh([np.flatnonzero(plane.part_ids == k)], append=True)
        assert part.is_watertight and part.is_winding_consistent, name
        assert part.volume > 0, name


@pytest.mark.parametrize("variant", VARIANTS)
def test_keypoints_lie_on_the_surface_seen_from_above(planes, variant):
    plane = planes[variant]
    P = plane.keypoints
    assert P.shape == (23, 3) and P.dtype == np.float64 and np.all(np.isfinite(P))
    assert plane.keypoint_names == KEYPOINT_NAMES
    _, distance, _ = trimesh.proximity.closest_point(plane.mesh, P)
    assert distance.max() < 1e-3
    z, tri = first_hits(plane.mesh, P[:, :2])
    np.testing.assert_allclose(z, P[:, 2], atol=1e-3)
    # each keypoint is on the part its name says
    part = np.array(PART_NAMES)[plane.part_ids[tri]]
    for name, p in zip(KEYPOINT_NAMES, part):
        side = name.split("_")[0]
        if name.startswith(("nose", "cockpit", "fuselage", "tail")):
            assert p == "fuselage", name
        elif name.startswith("fin"):
            assert p == "fin", name
        else:
            kind = {"wing": "wing", "engine": "nacelle", "stabiliser": "stabiliser"}
            assert p == f"{kind[name.split('_')[1]]}_{side}", name


@pytest.mark.parametrize("variant", VARIANTS)
def test_keypoints_sit_where_their_names_say(planes, variant):
    plane = planes[variant]
    P = {n: p for n, p in zip(KEYPOINT_NAMES, plane.keypoints)}
    xs = plane.keypoints[:, 0]
    assert P["nose"][0] == xs.max()
    assert P["nose"][0] > P["cockpit"][0] > P["fuselage_front"][0] > P["fuselage_mid"][0]
    assert P["fuselage_mid"][0] > P["fuselage_rear"][0] > P["fin_root"][0]
    assert min(P["tail_end"][0], P["fin_tip_trailing"][0]) == xs.min()
    assert P["fin_tip_leading"][2] == P["fin_tip_trailing"][2] == plane.keypoints[:, 2].max()
    assert P["left_wing_tip_leading"][1] == plane.keypoints[:, 1].max()
    lw = "left_wing_"
    assert P[lw + "root_leading"][0] > P[lw + "root_trailing"][0]
    assert P[lw + "tip_leading"][0] > P[lw + "tip_trailing"][0]
    assert P[lw + "root_leading"][0] - P[lw + "tip_leading"][0] > 5  # swept back
    assert P[lw + "tip_leading"][2] > P[lw + "root_leading"][2]  # dihedral
    assert P["left_engine_front"][0] > P[lw + "root_leading"][0]  # nacelle ahead of the wing
    assert P["left_engine_front"][2] < P[lw + "root_leading"][2]  # and under it
    assert P["left_stabiliser_tip"][1] > P["left_stabiliser_root"][1] > 0
    assert P["fin_tip_leading"][0] > P["fin_tip_trailing"][0]
    # the cockpit keypoint is on the dark window band, the engine front on the intake lip
    livery = GEOMETRIES[variant].livery
    _, tri = first_hits(plane.mesh, plane.keypoints[[IDX["cockpit"], IDX["left_engine_front"]], :2])
    colors = plane.mesh.visual.face_colors[tri, :3]
    np.testing.assert_array_equal(colors, [livery.window, livery.metal])


@pytest.mark.parametrize("variant", VARIANTS)
def test_left_and_right_keypoints_mirror_each_other(planes, variant):
    P = planes[variant].keypoints
    for name in KEYPOINT_NAMES:
        if name.startswith("left_"):
            right = IDX["right_" + name[5:]]
            np.testing.assert_allclose(P[IDX[name]] * [1, -1, 1], P[right], atol=1e-9)
        elif not name.startswith("right_"):
            assert P[IDX[name], 1] == pytest.approx(0.0, abs=1e-12)


def test_default_airliner_keypoints_are_the_table(planes):
    plane = planes["airliner"]
    np.testing.assert_allclose(plane.keypoints, airliner_keypoints(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(build_airplane().keypoints, plane.keypoints, atol=0, rtol=0)


def test_variants_differ(planes):
    for i, a in enumerate(VARIANTS):
        for b in VARIANTS[i + 1 :]:
            pa, pb = planes[a], planes[b]
            assert np.abs(pa.keypoints - pb.keypoints).max() > 0.5, (a, b)
            assert not np.allclose(pa.mesh.bounds, pb.mesh.bounds), (a, b)
            ca = {tuple(c) for c in pa.mesh.visual.face_colors}
            cb = {tuple(c) for c in pb.mesh.visual.face_colors}
            assert ca != cb, (a, b)
    assert planes["swept"].mesh.extents[1] > planes["airliner"].mesh.extents[1]
    assert planes["stretched"].mesh.extents[0] > planes["airliner"].mesh.extents[0] + 4


def test_keypoints_are_read_only(planes):
    with pytest.raises(ValueError):
        planes["airliner"].keypoints[0, 0] = 1.0


def test_unknown_variant_is_refused():
    with pytest.raises(ValueError, match="variant: unknown airplane variant 'glider'"):
        build_airplane("glider")


def test_save_and_load_round_trip(planes, saved):
    mesh_path, json_path, _ = saved
    plane = planes["airliner"]
    assert mesh_path.suffix == ".ply" and json_path.suffix == ".json"
    loaded = load_airplane(mesh_path, json_path)
    assert loaded.name == "airliner" and loaded.keypoint_names == KEYPOINT_NAMES
    np.testing.assert_array_equal(loaded.keypoints, plane.keypoints)
    assert loaded.ground_z == plane.ground_z
    np.testing.assert_allclose(loaded.mesh.bounds, plane.mesh.bounds, atol=1e-5)
    assert len(loaded.mesh.faces) == len(plane.mesh.faces)
    np.testing.assert_array_equal(loaded.mesh.visual.face_colors, plane.mesh.visual.face_colors)
    assert not list(mesh_path.parent.glob(".*.tmp"))  # no leftovers of the atomic write


def test_load_orders_keypoints_and_paints_uncoloured_meshes(planes, saved, tmp_path):
    plane = planes["airliner"]
    _, _, doc = saved
    bare = trimesh.Trimesh(plane.mesh.vertices, plane.mesh.faces, process=False)
    (tmp_path / "bare.obj").write_text(bare.export(file_type="obj"))
    doc = dict(doc, keypoints=doc["keypoints"][::-1])  # any order in the file
    del doc["ground_z"], doc["name"]
    (tmp_path / "kp.json").write_text(json.dumps(doc))
    loaded = load_airplane(tmp_path / "bare.obj", tmp_path / "kp.json")
    np.testing.assert_allclose(loaded.keypoints, plane.keypoints, atol=1e-12)
    assert loaded.name == "bare"
    assert loaded.ground_z == pytest.approx(loaded.mesh.bounds[0, 2])
    colors = np.asarray(loaded.mesh.visual.face_colors)
    assert colors.shape == (len(loaded.mesh.faces), 4)
    assert np.all(colors == DEFAULT_RGBA)


def test_load_merges_a_glb_scene(planes, saved, tmp_path):
    plane = planes["airliner"]
    _, json_path, _ = saved
    half = len(plane.mesh.faces) // 2
    scene = trimesh.Scene(
        [
            plane.mesh.submesh([np.arange(half)], append=True),
            plane.mesh.submesh([np.arange(half, len(plane.mesh.faces))], append=True),
        ]
    )
    (tmp_path / "plane.glb").write_bytes(scene.export(file_type="glb"))
    loaded = load_airplane(tmp_path / "plane.glb", json_path)
    assert len(loaded.mesh.faces) == len(plane.mesh.faces)
    np.testing.assert_allclose(loaded.mesh.bounds, plane.mesh.bounds, atol=1e-5)
    assert len(np.unique(loaded.mesh.visual.face_colors, axis=0)) >= 4


def _edit(doc, change):
    doc = json.loads(json.dumps(doc))
    change(doc)
    return doc


def _set_xyz(name, xyz):
    def change(doc):
        next(k for k in doc["keypoints"] if k["name"] == name)["xyz"] = xyz

    return change


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["keypoints"].pop(3), "missing \\['fuselage_mid'\\]"),
        (lambda d: d["keypoints"].append({"name": "propeller", "xyz": [0, 0, 0]}), "propeller"),
        (
            lambda d: d["keypoints"].append(dict(d["keypoints"][0])),
            "duplicate keypoint name 'nose'",
        ),
        (_set_xyz("nose", [18.8, 0.0, math.nan]), "finite"),
        (_set_xyz("nose", [18.8, 0.0]), "\\[x, y, z\\]"),
        (_set_xyz("nose", ["a", "b", "c"]), "\\[x, y, z\\]"),
        (_set_xyz("fuselage_mid", [0.0, 0.0, 2.98]), "within 0.25 m.*fuselage_mid \\(1.00 m\\)"),
        (lambda d: d.update(units="ft"), "units"),
        (lambda d: d.update(ground_z="low"), "ground_z"),
        (lambda d: d.pop("keypoints"), "'keypoints' list"),
    ],
)
def test_load_refuses_bad_keypoints(saved, tmp_path, change, message):
    mesh_path, _, doc = saved
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(doc, change)))
    with pytest.raises(ValueError, match="keypoints_json: .*" + message):
        load_airplane(mesh_path, bad)


def test_load_refuses_missing_files_and_bad_meshes(saved, tmp_path):
    mesh_path, json_path, _ = saved
    with pytest.raises(FileNotFoundError, match="mesh_path: no such file"):
        load_airplane(tmp_path / "nope.ply", json_path)
    with pytest.raises(FileNotFoundError, match="keypoints_json: no such file"):
        load_airplane(mesh_path, tmp_path / "nope.json")
    (tmp_path / "garbage.ply").write_bytes(b"not a mesh at all")
    with pytest.raises(ValueError, match="mesh_path: cannot load a mesh"):
        load_airplane(tmp_path / "garbage.ply", json_path)
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="mesh_path: expected a triangle mesh with faces"):
        load_airplane(tmp_path / "points.obj", json_path)
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ValueError, match="keypoints_json: .* is not valid JSON"):
        load_airplane(mesh_path, tmp_path / "broken.json")


@pytest.fixture(scope="module")
def user_files(tmp_path_factory):
    """The default airliner as a user's files: (mesh_path, json document, lowest z)."""
    plane = build_airplane("airliner")
    mesh_path, json_path = save_airplane(plane, tmp_path_factory.mktemp("plane"))
    return mesh_path, json.loads(json_path.read_text()), float(plane.mesh.bounds[0, 2])


def _write(tmp_path, doc):
    path = tmp_path / "kp.json"
    path.write_text(json.dumps(doc))
    return path


def test_all_keypoints_at_one_point_are_refused(user_files, tmp_path):
    mesh_path, doc, _ = user_files
    nose = doc["keypoints"][0]["xyz"]
    doc = dict(doc, keypoints=[{"name": k["name"], "xyz": nose} for k in doc["keypoints"]])
    with pytest.raises(ValueError, match="^keypoints_json: expected keypoints that span the"):
        load_airplane(mesh_path, _write(tmp_path, doc))


def test_keypoints_collinear_seen_from_above_are_refused(user_files, tmp_path):
    """Every keypoint moved onto the fuselage's top line (y = 0, all on the surface)."""
    mesh_path, doc, _ = user_files
    axis = [k["xyz"] for k in doc["keypoints"] if k["xyz"][1] == 0.0]
    keypoints = [
        {"name": k["name"], "xyz": axis[i % len(axis)]} for i, k in enumerate(doc["keypoints"])
    ]
    with pytest.raises(ValueError, match="^keypoints_json: expected keypoints that are not colli"):
        load_airplane(mesh_path, _write(tmp_path, dict(doc, keypoints=keypoints)))


@pytest.mark.parametrize("offset", [-1000.0, -30.0, 2.0])
def test_a_ground_plane_away_from_the_mesh_is_refused(user_files, tmp_path, offset):
    """1000 m or 30 m below the lowest point (the airplane floats out of the picture), or
    2 m above it (it sinks into the ground)."""
    mesh_path, doc, lowest = user_files
    doc = dict(doc, ground_z=lowest + offset)
    with pytest.raises(ValueError, match="^keypoints_json: expected 'ground_z' between"):
        load_airplane(mesh_path, _write(tmp_path, doc))


def test_the_dataset_cli_refuses_before_writing(user_files, tmp_path, capsys):
    from data_gen.cli import main

    mesh_path, doc, lowest = user_files
    out = tmp_path / "out"
    json_path = _write(tmp_path, dict(doc, ground_z=lowest - 1000.0))
    with pytest.raises(SystemExit) as exit_:
        main(
            [
                "dataset",
                "--out",
                str(out),
                "--n",
                "1",
                "--size",
                "32x20",
                "--mesh",
                str(mesh_path),
                "--keypoints",
                str(json_path),
            ]
        )
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "ground_z" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kp.json"]
