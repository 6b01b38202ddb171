"""Importing a Blender scene (``.blend``) as a canonical sequence: conversion, agreement with Blender's
own projection, bad input.

Tests that open a ``.blend`` need Blender's Python (``.venv-blender`` or
``$UNDREAM_BLENDER_PYTHON``); without it they skip with the reason, and fail
where ``UNDREAM_REQUIRE_SERVICES`` is set (CI). The conversion itself, and
what happens without Blender, are tested without it.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import service_missing
from projection import centroid, load, project, visible_mask
from undream.bridge.blender_import import BlendSource, ply_bytes, sequence_from_blend, sequence_from_export
from undream.errors import BridgeError, SpecError, UndreamError
from undream.scene.mesh import read_ply

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent


# --- the conversion, on a hand-written export (no Blender) ------------------------------------------

def _export(**over) -> dict:
    """A camera at Blender (0, −5, 1) turned 90° about X (looking along Blender +Y, up +Z), 64×48 px,
    sensor 36 mm over the width at 18 mm (90° horizontal); a one-triangle object at the origin."""
    cam = [[1, 0, 0, 0], [0, 0, -1, -5], [0, 1, 0, 1], [0, 0, 0, 1]]
    frame = {"frame": 3, "camera": {"matrix_world": cam,
                                    "view_frame": [[1, 0.75, -1], [1, -0.75, -1], [-1, -0.75, -1], [-1, 0.75, -1]]},
             "object": {"matrix_world": np.eye(4).tolist()}}
    data = {"format": "undream-blender-export", "version": 1, "fps": 25.0, "resolution": [64, 48],
            "pixel_aspect": [1, 1], "camera": {"name": "Cam"},
            "object": {"name": "Tri.001", "mesh": {"vertices": [[0, 0, 0], [1, 0, 0], [0, 0, 1]],
                                                    "triangles": [[0, 1, 2]],
                                                    "uvs": [[[0, 0], [1, 0], [0, 1]]],
                                                    "normals": [[[0, -1, 0]] * 3]}},
            "frames": [frame, {**frame, "frame": 5}]}
    data.update(over)
    return data


def test_export_converts_axes_camera_and_uvs():
    seq, meshes = sequence_from_export(_export(), name="my scene")
    mesh = meshes["Tri_001"]
    cam = np.array(seq.frames[0].camera.to_world.matrix)
    # Blender +Y (the view) is canonical −Z; Blender +Z (up) is canonical +Y; the image's left is −X.
    assert np.allclose(cam[:3, 2], [0, 0, -1]) and np.allclose(cam[:3, 1], [0, 1, 0])
    assert np.allclose(cam[:3, 0], [-1, 0, 0]) and np.allclose(cam[:3, 3], [0, 1, 5])
    assert seq.frames[0].camera.fov_deg == pytest.approx(90.0) and seq.frames[0].camera.resolution == (64, 48)
    assert [f.index for f in seq.frames] == [3, 5] and seq.frames[1].time == pytest.approx(2 / 25)
    assert seq.name == "my_scene" and seq.asset.name == "Tri_001" and seq.source == "blender"
    # Blender's (x, y, z) is canonical (x, z, −y); v flips; the face normal stays outward.
    order = np.lexsort(mesh.vertices.T)
    assert np.allclose(mesh.vertices[order], [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert np.allclose(mesh.uvs[order], [[0, 1], [1, 1], [0, 0]])
    assert np.allclose(mesh.normals, [0, 0, 1])
    a, b, c = mesh.vertices[mesh.faces[0]]
    assert np.cross(b - a, c - a) @ [0, 0, 1] > 0  # winding kept: counter-clockwise seen from the normal
    assert len(ply_bytes(mesh)) > 0


@pytest.mark.parametrize("change, message", [
    ({"pixel_aspect": [1, 2]}, "square pixels"),
    ({"frames": []}, "frame range holds no frame"),
    ({"resolution": [64, 0]}, "resolution"),
])
def test_export_bad_values_are_one_line(change, message):
    with pytest.raises((BridgeError, SpecError), match=message) as err:
        sequence_from_export(_export(**change))
    assert "\n" not in str(err.value)


def test_lens_shift_and_negative_frames_are_refused():
    data = _export()
    data["frames"][0]["camera"]["view_frame"] = [[1.2, 0.75, -1], [1.2, -0.75, -1], [-0.8, -0.75, -1],
                                                 [-0.8, 0.75, -1]]
    with pytest.raises(BridgeError, match=r"frames\[0\].camera: lens shift"):
        sequence_from_export(data)
    data = _export()
    data["frames"][0]["frame"] = -1
    with pytest.raises(BridgeError, match=r"frames\[0\].frame: must be a frame number >= 0"):
        sequence_from_export(data)


def test_export_actors_convert_like_the_object():
    data = _export()
    mesh = data["object"]["mesh"]
    data["actors"] = [{"name": "Post", "mesh": mesh}]
    moved = [[1, 0, 0, 2], [0, 1, 0, 3], [0, 0, 1, 4], [0, 0, 0, 1]]  # Blender (2, 3, 4)
    for f in data["frames"]:
        f["actors"] = {"Post": {"matrix_world": moved}}
    seq, meshes = sequence_from_export(data)
    assert [a.name for a in seq.actors] == ["Post"] and set(meshes) == {"Tri_001", "Post"}
    pose = np.array(seq.frames[1].actors[0].to_world.matrix)
    assert np.allclose(pose[:3, 3], [2, 4, -3]) and np.allclose(pose[:3, :3], np.eye(3))  # (x, z, −y)
    del data["frames"][1]["actors"]
    with pytest.raises(BridgeError, match=r"frames\[1\].actors: must hold the matrix of every actor \(Post\)"):
        sequence_from_export(data)


# --- without Blender ---------------------------------------------------------------------------------

def test_missing_interpreter_is_one_line_and_writes_nothing(tmp_path):
    blend = tmp_path / "scene.blend"
    blend.write_bytes(b"BLENDER-v500 not really")
    missing = tmp_path / "nowhere" / "python"
    with pytest.raises(BridgeError) as err:
        sequence_from_blend(BlendSource(blend, "Crate", python=str(missing)), cache_dir=tmp_path / "cache")
    msg = str(err.value)
    assert "\n" not in msg and str(blend) in msg and str(missing) in msg and "UNDREAM_BLENDER_PYTHON" in msg
    assert not (tmp_path / "cache").exists()


def test_blend_without_object_option_is_one_line(tmp_path):
    blend = tmp_path / "scene.blend"
    blend.write_bytes(b"BLENDER")
    from undream.scene.sources import sequence_from_file

    with pytest.raises(SpecError, match=r"scene.blend: .*--object NAME"):
        sequence_from_file(blend)


# --- with Blender ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    """tests/make_blend.py's scene and Blender's own projections of the crate (see there)."""
    from undream.bridge.blender_python import blender_python, bpy_problem

    python = blender_python()
    problem = bpy_problem(python)
    if problem is not None:
        service_missing(f"Blender's Python is not usable ({problem[1]}); {python}")
    out = tmp_path_factory.mktemp("blend") / "scene.blend"
    subprocess.run([str(python), str(HERE / "make_blend.py"), str(out)], check=True, capture_output=True,
                   timeout=300)
    return out, json.loads(out.with_suffix(".json").read_text())


def test_blend_matches_blenders_projection(blend, tmp_path, mi):
    """Every frame: the crate's origin and its 8 corners, imported and projected by the independent
    pinhole model, land within 1.5 px of Blender's ``world_to_camera_view``; Mitsuba's mask agrees."""
    from undream.scenedir.init import InitOptions, init_scene

    path, expected = blend
    seq = sequence_from_blend(BlendSource(path, "Crate", actors=("Post",)), cache_dir=tmp_path / "cache")
    assert [f.index for f in seq.frames] == [1, 2, 3, 4, 5] and seq.fps == 10.0
    mesh, post = read_ply(seq.asset.mesh), read_ply(seq.actors[0].mesh)
    assert mesh.n_faces == 12 and mesh.uvs.min() >= 0 and mesh.uvs.max() <= 1
    assert seq.actors[0].name == "Post" and post.n_faces == 12 and np.ptp(post.uvs, axis=0).max() == 0  # no UVs: one
    worst = 0.0
    for f, want in zip(seq.frames, expected):
        cam = f.camera.to_json()
        m = np.array(f.object_to_world.matrix)
        origin, _ = project(m[None, :3, 3], cam)
        worst = max(worst, float(np.linalg.norm(origin[0] - want["origin"])))
        for shape, pose, points in ((mesh, m, want["corners"]),
                                    (post, np.array(f.actors[0].to_world.matrix), want["post"])):
            corners = (pose @ np.c_[shape.vertices, np.ones(shape.n_vertices)].T).T[:, :3]
            px, depth = project(corners, cam)
            assert (depth > 0).all()
            for point in points:  # each Blender corner is one of the imported mesh's vertices
                worst = max(worst, float(np.linalg.norm(px - point, axis=1).min()))
    print(f"worst distance to Blender's projection: {worst:.2e} px")
    assert worst < 1.5
    scene = init_scene(BlendSource(path, "Crate"), tmp_path / "scene", InitOptions(verify_spp=4))
    from undream.scenedir.verify import read_mask

    data = load(scene)
    for f in data["frames"]:
        mine, theirs = read_mask(scene, f["index"]), visible_mask(scene, f, data)
        assert theirs.sum() >= 12 and (mine & theirs).sum() / (mine | theirs).sum() > 0.8
        assert np.linalg.norm(centroid(mine) - centroid(theirs)) <= 1.5
    meta = json.loads((scene / "metadata.json").read_text())
    assert json.loads(meta["spec"])["object"] == "Crate" and meta["source"] == "blender"
    from undream.sim import make_backend

    cycles = make_backend("blender", scene, threads=2)  # and back into Blender: Cycles sees the same object
    try:
        for f in data["frames"]:
            mine, theirs = cycles.coverage(f["index"], spp=16) > 0.5, read_mask(scene, f["index"])
            assert (mine & theirs).sum() / (mine | theirs).sum() > 0.8, f"frame {f['index']}"
    finally:
        cycles.close()


@pytest.mark.parametrize("name, camera, message", [
    ("Nope", None, "no object named 'Nope' (mesh objects: Bare, Crate, Post)"),
    ("Bare", None, "object 'Bare' has no UV map"),
    ("Crate", "Flat", "camera 'Flat' is ORTHO"),
    ("Crate", "Ghost", "no camera named 'Ghost'"),
    ("Crate", ("Crate",), "--actor names each object once, and not the adversarial object 'Crate'"),
    ("Crate", ("Nobody",), "no object named 'Nobody'"),
])
def test_bad_blend_input_is_one_line(blend, tmp_path, name, camera, message):
    path, _ = blend
    camera, actors = (None, camera) if isinstance(camera, tuple) else (camera, ())
    with pytest.raises(BridgeError) as err:
        sequence_from_blend(BlendSource(path, name, camera, actors), cache_dir=tmp_path / "cache")
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and message in msg and "\n" not in msg
    assert not (tmp_path / "cache").exists()


def test_cli_init_blend(blend, tmp_path):
    """``undream init scene.blend --object NAME``: a scene directory; a missing object: one line, exit 2,
    nothing written."""
    path, _ = blend
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    out = tmp_path / "bad"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(path), "--object", "Nope", "--out",
                          str(out), "--no-progress"], capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and str(path) in lines[0] and "'Nope'" in lines[0], res.stderr
    assert not out.exists()
    out = tmp_path / "good"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(path), "--object", "Crate", "--camera",
                          "Cam", "--actor", "Post", "--out", str(out), "--verify-spp", "1", "--no-progress"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert len(list((out / "frames").glob("sim_*.xml"))) == 5 and (out / "meshes" / "object.ply").is_file()
    assert (out / "meshes" / "Post.ply").is_file()
    assert "meshes/Post.ply" in (out / "frames" / "sim_0003.xml").read_text()


def test_cli_object_option_only_for_blend(tmp_path):
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(ROOT / "examples" / "bin_park.yaml"),
                          "--object", "Crate", "--out", str(tmp_path / "x")], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert res.returncode == 2 and "--object, --camera and --actor are for .blend files only" in res.stderr
    assert not (tmp_path / "x").exists()
