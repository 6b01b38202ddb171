"""Realistic objects fetched at setup (issue 40): the AC3D reader, ``asset:NAME`` in scene files, and
the converted car and person (deploy/fetch_assets.py; docs/scenes.md#realistic-objects-fetched-at-setup).

The reader and the names are tested on files written here; the converted assets only where
``deploy/setup.sh`` put them in this machine's cache (skipped, saying so, where it did not).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from undream.errors import AssetError, SpecError
from undream.scene import fetched
from undream.scene.ac3d import ac3d_mesh, parse_ac3d
from undream.scene.builtin import box
from undream.scene.mesh import read_ply, write_ply
from undream.scene.trajectory import sequence_from_trajectory
from undream.settings import load_local

ROOT = Path(__file__).resolve().parents[1]

# Two objects under a group moved up 1 m: a quad as a TORCS triangle strip (two UV pairs per ref,
# base texture first; a repeated vertex makes a degenerate triangle that is dropped), a polygon
# triangle and a line (skipped), and a kid moved by its own loc with another texture.
TINY_ACC = """AC3Db
MATERIAL "m" rgb 1 1 1  amb 1 1 1  emis 0 0 0  spec 0 0 0  shi 0  trans 0
OBJECT world
kids 1
OBJECT group
loc 0 1 0
kids 2
OBJECT poly
name "body"
texture "car.rgb" base
texture "car.rgb" skids
numvert 5
0 0 0 0 0 1
1 0 0 0 0 1
0 1 0 0 0 1
1 1 0 0 0 1
2 0 0 0 0 1
numsurf 3
SURF 0x34
mat 0
refs 5
0 0.0 0.0 0.9 0.9
1 1.0 0.0 0.9 0.9
2 0.0 1.0 0.9 0.9
3 1.0 1.0 0.9 0.9
3 1.0 1.0 0.9 0.9
SURF 0x30
mat 0
refs 3
1 0.5 0.25 0.9 0.9
4 1.0 0.25 0.9 0.9
3 1.0 0.75 0.9 0.9
SURF 0x32
mat 0
refs 2
0 0 0 0 0
4 0 0 0 0
kids 0
OBJECT poly
name "glass"
texture "glass.rgb"
loc 5 0 0
numvert 3
0 0 0
1 0 0
0 1 0
numsurf 1
SURF 0x20
mat 0
refs 3
0 0 0
1 1 0
2 0 1
kids 0
"""


# --- the AC3D reader ---------------------------------------------------------------------------

def test_the_ac3d_reader_reads_parts_textures_uvs_and_placement():
    parts = parse_ac3d(TINY_ACC, "tiny.acc")
    assert [(p.name, p.texture) for p in parts] == [("body", "car.rgb"), ("glass", "glass.rgb")]
    body = ac3d_mesh(parts, "car.rgb", scale=2.0)
    assert body.n_faces == 3  # the strip's two triangles (its degenerate third dropped) and the polygon
    assert body.n_vertices == 7  # vertices 1 and 3 appear with two UVs each: split
    lo, hi = body.bounds()
    np.testing.assert_allclose(lo, [0, 2, 0])  # the group's loc (1 m up), then scale 2
    np.testing.assert_allclose(hi, [4, 4, 0])
    # base UVs (not the skids pair), v flipped to undream's rows-down convention
    uv_of = {tuple(np.round(v / 2 - [0, 1, 0], 6)): tuple(np.round(t, 6))
             for v, t in zip(body.vertices, body.uvs)}
    assert uv_of[(0.0, 0.0, 0.0)] == (0.0, 1.0) and uv_of[(0.0, 1.0, 0.0)] == (0.0, 0.0)
    assert uv_of[(2.0, 0.0, 0.0)] == (1.0, 0.75)
    # every triangle wound counter-clockwise seen along the file's normals (+Z), strips included
    assert (body.face_normals()[:, 2] > 0.99).all()
    glass = ac3d_mesh(parts, "glass.rgb")
    np.testing.assert_allclose(glass.bounds()[0], [5, 1, 0])  # its own loc on top of the group's


def test_the_first_part_s_texture_is_the_default():
    parts = parse_ac3d(TINY_ACC)
    assert ac3d_mesh(parts).n_faces == ac3d_mesh(parts, "car.rgb").n_faces


@pytest.mark.parametrize(("text", "needles"), [
    ("OBJ world\n", ["tiny.acc", "not an AC3D file"]),
    (TINY_ACC.replace("loc 0 1 0", "wobble 3"), ["tiny.acc", "line 6", "unknown AC3D token 'wobble'"]),
    (TINY_ACC.replace("4 1.0 0.25", "9 1.0 0.25"), ["tiny.acc", "refs", "vertex index 9", "[0, 5)"]),
    (TINY_ACC.replace("SURF 0x30", "SURF 0x37"), ["tiny.acc", "unknown surface type 7"]),
    (TINY_ACC.replace("loc 0 1 0", "loc 0 nan 0"), ["tiny.acc", "loc", "finite"]),
    (TINY_ACC[:TINY_ACC.index("numsurf 3")], ["tiny.acc", "ends early"]),
])
def test_bad_ac3d_files_are_one_line(text, needles):
    with pytest.raises(AssetError) as err:
        parse_ac3d(text, "tiny.acc")
    msg = str(err.value)
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg


def test_a_texture_no_part_has_is_refused():
    with pytest.raises(AssetError, match="no part of the model has the texture 'tyre.rgb'"):
        ac3d_mesh(parse_ac3d(TINY_ACC), "tyre.rgb")


# --- asset:NAME in scene files -------------------------------------------------------------------

def _cache_with_box(cache_home: Path) -> Path:
    """A converted asset ``asset:crate`` (a 1 m box and a 4×4 texture) under ``cache_home``."""
    folder = fetched.assets_root(cache_home / "undream") / "crate"
    folder.mkdir(parents=True)
    write_ply(box((1, 1, 1), (0, 0.5, 0)), folder / fetched.MESH_FILE)
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(folder / fetched.TEXTURE_FILE)
    return folder


def _spec(mesh: str = "asset:crate", init: object = "asset:crate", res: int = 16) -> dict:
    return {"name": "crate", "frames": 2,
            "camera": {"fov": 40, "resolution": [res, res], "path": {"type": "static", "position": [0, 1, 4]}},
            "object": {"asset": {"name": "crate", "mesh": mesh, "texture": {"resolution": [8, 8], "init": init}},
                       "path": {"type": "static", "position": [0, 0, 0]}}}


def test_an_asset_name_resolves_to_the_cached_files(tmp_path):
    folder = _cache_with_box(tmp_path)
    seq = sequence_from_trajectory(_spec(), cache_dir=tmp_path / "undream")
    assert seq.asset.mesh == str(folder / "mesh.ply")
    assert seq.asset.texture.init == str(folder / "texture.png")
    assert read_ply(seq.asset.mesh).n_faces == 12


@pytest.mark.parametrize(("spec", "needles"), [
    (_spec(mesh="asset:nothing"), ["object.asset.mesh", "'asset:nothing' is not in the asset cache",
                                   "run ./deploy/setup.sh"]),
    (_spec(mesh="asset:Bad/../name"), ["object.asset.mesh", "is not an asset name"]),
    (_spec(init="asset:nothing"), ["object.asset.texture.init", "'asset:nothing'", "run ./deploy/setup.sh"]),
])
def test_a_missing_or_malformed_asset_name_is_one_line(spec, needles, tmp_path):
    _cache_with_box(tmp_path)
    with pytest.raises(SpecError) as err:
        sequence_from_trajectory(spec, cache_dir=tmp_path / "undream")
    assert "\n" not in str(err.value)
    for needle in needles:
        assert needle in str(err.value)


def test_an_actor_asset_has_no_starting_texture(tmp_path):
    folder = _cache_with_box(tmp_path)
    (folder / fetched.TEXTURE_FILE).unlink()
    with pytest.raises(SpecError, match="texture.init: 'asset:crate' .* the asset has no starting texture"):
        sequence_from_trajectory(_spec(), cache_dir=tmp_path / "undream")


def test_the_library_reads_no_cache_folder_from_the_environment(tmp_path, monkeypatch):
    """The asset cache is passed from the edge (settings): a caller that passes none gets one line,
    whatever $XDG_CACHE_HOME says."""
    _cache_with_box(tmp_path)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    with pytest.raises(SpecError) as err:
        sequence_from_trajectory(_spec())
    assert "\n" not in str(err.value)
    assert "object.asset.mesh: 'asset:crate' names a fetched asset, but no asset cache was given" in str(err.value)


def _run_check(tmp_path: Path, spec: dict) -> subprocess.CompletedProcess:
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(spec))
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({
        "scene": "scene.yaml", "victim": "bundled:classifier", "label": "car", "loss": "ce",
        "attack": {"name": "pgd", "steps": 1},
        "sim_spp": 1, "grad_spp": 1, "eval_spp": 1}))
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    return subprocess.run([sys.executable, "-m", "undream.cli", "run", str(tmp_path / "run.yaml"),
                           "--out", str(tmp_path / "out"), "--check"],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)


def test_run_check_names_the_field_and_setup_when_the_asset_is_missing(tmp_path):
    res = _run_check(tmp_path, _spec(mesh="asset:p406", init=[0.5, 0.5, 0.5]))
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    for needle in ("scene.yaml", "object.asset.mesh", "'asset:p406' is not in the asset cache",
                   str(tmp_path / "cache" / "undream" / "assets" / "p406" / "mesh.ply"), "./deploy/setup.sh"):
        assert needle in lines[0]
    assert not (tmp_path / "out").exists()


def test_run_check_accepts_a_cached_asset(tmp_path):
    _cache_with_box(tmp_path / "cache")
    res = _run_check(tmp_path, _spec())
    assert res.returncode == 0, res.stderr
    assert not (tmp_path / "out").exists()


# --- the converted car and person, where setup put them -------------------------------------------

CONVERTED = fetched.assets_root(load_local().undream_cache)
HAVE = all((CONVERTED / n / fetched.MESH_FILE).is_file() for n in ("p406", "p406_wheels", "person_clothes", "person_body"))
needs_cache = pytest.mark.skipif(not HAVE, reason=f"the converted assets are not in {CONVERTED}: "
                                 "run ./deploy/setup.sh (or .venv/bin/python deploy/fetch_assets.py)")


@needs_cache
@pytest.mark.parametrize(("example", "axis", "size_m"), [("car_street", 2, 4.60), ("person_street", 1, 1.75)])
def test_the_converted_assets_load_as_scenes_at_real_size(example, axis, size_m, tmp_path):
    spec = yaml.safe_load((ROOT / "examples" / f"{example}.yaml").read_text())
    spec["frames"], spec["camera"]["resolution"] = 2, [32, 32]
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(spec))
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(tmp_path / "scene.yaml"),
                          "--out", str(tmp_path / "scene"), "--verify-spp", "1", "--no-progress"],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    obj = read_ply(tmp_path / "scene" / "meshes" / "object.ply")
    meshes = [obj] + [read_ply(p) for p in (tmp_path / "scene" / "meshes").glob("*.ply") if p.stem != "object"]
    lo = np.min([m.bounds()[0] for m in meshes], axis=0)
    hi = np.max([m.bounds()[1] for m in meshes], axis=0)
    assert hi[axis] - lo[axis] == pytest.approx(size_m, abs=0.01)
    assert lo[1] == pytest.approx(0.0, abs=1e-3)  # standing on the ground
    assert (obj.uvs >= -1e-6).all() and (obj.uvs <= 1 + 1e-6).all()
    texture = np.asarray(Image.open(tmp_path / "scene" / "textures" / "adv_texture.png"))
    assert texture.std() > 10  # the livery or the shirt's print, not a flat colour
    for mask in sorted((tmp_path / "scene" / "verify").glob("mask_*.png")):
        assert (np.asarray(Image.open(mask)) > 0).mean() > 0.01  # the object is in view
    meta = json.loads((tmp_path / "scene" / "metadata.json").read_text())
    assert str(CONVERTED) in json.dumps(meta)  # the scene records the cached file it came from


@needs_cache
def test_fetch_assets_check_finds_everything_converted():
    res = subprocess.run([sys.executable, str(ROOT / "deploy" / "fetch_assets.py"), "--check"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "everything is in" in res.stdout


def test_the_lock_pins_every_package_and_file():
    lock = json.loads((ROOT / "deploy" / "assets.lock.json").read_text())
    for pkg in lock["packages"]:
        assert pkg["kind"] == "deb" and pkg["version"] and pkg["licence"]
        for f in pkg["files"].values():
            assert len(f["sha256"]) == 64 and f["to"].startswith("assets/src/")
