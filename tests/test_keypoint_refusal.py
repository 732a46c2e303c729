"""Degenerate user keypoint JSON (issue 29, point 6): keypoints that do not span the airplane
and a ground plane away from the mesh are refused when the airplane is loaded, before
anything is rendered; a keypoint behind the camera is never marked visible."""

from __future__ import annotations

import json

import numpy as np
import pytest

from data_gen.airplane import build_airplane, load_airplane, save_airplane
from data_gen.keypoints import KEYPOINT_NAMES
from data_gen.render import Frame
from data_gen.scene import keypoint_visibility


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """The default airliner as a user's files: (mesh_path, json document, lowest z)."""
    plane = build_airplane("airliner")
    mesh_path, json_path = save_airplane(plane, tmp_path_factory.mktemp("plane"))
    return mesh_path, json.loads(json_path.read_text()), float(plane.mesh.bounds[0, 2])


def _write(tmp_path, doc):
    path = tmp_path / "kp.json"
    path.write_text(json.dumps(doc))
    return path


def test_all_keypoints_at_one_point_are_refused(saved, tmp_path):
    mesh_path, doc, _ = saved
    nose = doc["keypoints"][0]["xyz"]
    doc = dict(doc, keypoints=[{"name": k["name"], "xyz": nose} for k in doc["keypoints"]])
    with pytest.raises(ValueError, match="^keypoints_json: expected keypoints that span the"):
        load_airplane(mesh_path, _write(tmp_path, doc))


def test_keypoints_collinear_seen_from_above_are_refused(saved, tmp_path):
    """Every keypoint moved onto the fuselage's top line (y = 0, all on the surface)."""
    mesh_path, doc, _ = saved
    axis = [k["xyz"] for k in doc["keypoints"] if k["xyz"][1] == 0.0]
    keypoints = [
        {"name": k["name"], "xyz": axis[i % len(axis)]} for i, k in enumerate(doc["keypoints"])
    ]
    with pytest.raises(ValueError, match="^keypoints_json: expected keypoints that are not colli"):
        load_airplane(mesh_path, _write(tmp_path, dict(doc, keypoints=keypoints)))


@pytest.mark.parametrize("offset", [-1000.0, -30.0, 2.0])
def test_a_ground_plane_away_from_the_mesh_is_refused(saved, tmp_path, offset):
    """1000 m or 30 m below the lowest point (the airplane floats out of the picture), or
    2 m above it (it sinks into the ground)."""
    mesh_path, doc, lowest = saved
    doc = dict(doc, ground_z=lowest + offset)
    with pytest.raises(ValueError, match="^keypoints_json: expected 'ground_z' between"):
        load_airplane(mesh_path, _write(tmp_path, doc))


def test_the_dataset_cli_refuses_before_writing(saved, tmp_path, capsys):
    from data_gen.cli import main

    mesh_path, doc, lowest = saved
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


def test_a_keypoint_behind_the_camera_is_not_visible():
    """Nothing drawn (depth 0): keypoints in front are inside but hidden; behind the camera,
    whose projection is a mirror image inside the frame, they are outside (0), not 2."""
    h, w = 20, 32
    frame = Frame(
        np.zeros((h, w, 3), np.uint8),
        np.zeros((h, w), np.float32),
        np.zeros((h, w), np.float32),
        np.full((h, w), -1, np.int32),
    )
    K = np.array([[30.0, 0, 16], [0, 30.0, 10], [0, 0, 1]])
    points = np.zeros((len(KEYPOINT_NAMES), 3))
    points[:, 0] = np.linspace(-1, 1, len(points))
    _, front = keypoint_visibility(frame, points, np.eye(3), np.array([0, 0, 50.0]), K)
    _, behind = keypoint_visibility(frame, points, np.eye(3), np.array([0, 0, -50.0]), K)
    assert (front == 1).all() and (behind == 0).all()
