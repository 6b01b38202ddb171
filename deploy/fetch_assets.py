#!/usr/bin/env python3
"""Fetch realistic objects from Debian packages and convert them into undream's asset cache.

Reads ``deploy/assets.lock.json`` (pinned package versions, the SHA-256 of
every file taken) and fetches with :mod:`fetch_models`'s rules into
``CACHE/assets/src`` (``CACHE``: ``$XDG_CACHE_HOME/undream``, default
``~/.cache/undream``, or ``--cache``). Then it converts them into
``CACHE/assets/NAME/`` folders that scene files name as ``asset:NAME``
(:mod:`undream.scene.fetched`): ``mesh.ply`` (canonical: Y up, metres,
UV-mapped), ``texture.png`` (the starting texture, sRGB, opaque) where the
asset is meant to be attacked, and ``asset.json`` (source, licence, scale,
the baked colour of an actor). Converted:

- ``p406``: TORCS's Peugeot 406 (``torcs-data``, GPL-2+), its ``.acc`` read
  by :mod:`undream.scene.ac3d`, 4.60 m long, front towards +Z, on the ground
  (y = 0), its livery (512², the ``.rgb``'s colour) as the texture;
  ``p406_wheels``: four plain tyres (the model has none), an actor.
- ``person_clothes``: the T-shirt and jeans of MORSE's MakeHuman man
  (``morse-simulator-data``, BSD-3) as one mesh with one atlas texture
  (1024×512: their textures resampled to 512² each, side by side); ``person_body``, ``person_shoes``,
  ``person_hair``, ``person_eyes``: the rest of him, actors, each with one
  colour baked from its texture (the texture's mean over the part's
  surface); ``person_shirt`` (with its texture) and ``person_jeans`` alone
  too. 1.75 m tall, facing +Z, feet at y = 0, in the pose the file holds.
  Blender's interpreter (``.venv-blender``) reads the ``.blend``
  (``deploy/blend_parts.py``).

An asset whose ``asset.json`` records the same sources and recipe is not
converted again; a conversion is written to a temporary folder and moved into
place whole. Errors are one line. Run by ``deploy/setup.sh``; by hand:
``.venv/bin/python deploy/fetch_assets.py [--cache DIR] [--check]``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
from PIL import Image

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from fetch_models import FetchError, default_cache, fetch, missing  # noqa: E402

from undream.color import linear_to_srgb, srgb_to_linear  # noqa: E402
from undream.errors import UndreamError  # noqa: E402
from undream.scene.ac3d import ac3d_mesh, read_ac3d  # noqa: E402
from undream.scene.builtin import cylinder  # noqa: E402
from undream.scene.fetched import ASSET_FILE, MESH_FILE, TEXTURE_FILE, assets_root  # noqa: E402
from undream.scene.mesh import Mesh, concat_meshes, write_ply  # noqa: E402

LOCK = HERE / "assets.lock.json"
RECIPE = 2  # raise when a conversion changes: every asset is converted again
BLENDER_PYTHON = HERE.parent / ".venv-blender" / "bin" / "python"
CAR_LENGTH_M = 4.60
PERSON_HEIGHT_M = 1.75
CLOTHES_SIDE = 512  # texels: the clothes' atlas is 1024×512 (plenty for a person 150 px tall)
# TORCS's p406.xml: axles at x = ±1.37 m, wheels at ±0.75/0.78 m; 16-inch rims, 235/55 tyres.
WHEEL_X_M, WHEEL_Z_M, WHEEL_RADIUS_M, WHEEL_WIDTH_M = 1.37, 0.765, 0.33, 0.22
PERSON_PARTS = {  # asset name → (MakeHuman object, its packed image)
    "person_shirt": ("MakeHuman skeleton_man1-tshirt02", "tshirt02_texture.png"),
    "person_body": ("MakeHuman skeleton_man1-male1591", "young_lightskinned_male_diffuse.png"),
    "person_jeans": ("MakeHuman skeleton_man1-jeans01", "jeans_basic_diffuse.png"),
    "person_shoes": ("MakeHuman skeleton_man1-classic_shoes_lres", "classicshoes_texture_diffuse.png"),
    "person_hair": ("MakeHuman skeleton_man1-mhair02", "male02_diffuse_black.png"),
    "person_eyes": ("MakeHuman skeleton_man1-eyes", "brown_eye.png"),
}
C = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # canonical → Blender; Blender → canonical is C.T
FACE_Z = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # a quarter turn about +Y, +X → +Z: the car and the man face +X in their files


class ConvertError(FetchError):
    """A fetched file could not be converted."""


# --- the car ---------------------------------------------------------------------------------------

def convert_car(src: Path) -> dict[str, dict[str, Any]]:
    """``p406`` and ``p406_wheels`` from ``src`` (the fetched .acc and .rgb): name → what to write."""
    mesh = ac3d_mesh(read_ac3d(src / "p406.acc"), "p406.rgb")
    lo, hi = mesh.bounds()
    k = CAR_LENGTH_M / (hi[0] - lo[0])
    centre = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    body = mesh.transformed(offset=-centre).scaled(k).transformed(FACE_Z)
    livery = np.asarray(Image.open(src / "p406.rgb").convert("RGB"))
    wheels = []
    for x in (-WHEEL_X_M, WHEEL_X_M):
        for z in (-WHEEL_Z_M, WHEEL_Z_M):
            tyre = cylinder(WHEEL_RADIUS_M, WHEEL_WIDTH_M)  # along +Y: turned to TORCS's axles (Z)
            wheels.append(tyre.transformed(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
                                           ((x - centre[0]) * k, WHEEL_RADIUS_M, (z - centre[2]) * k)))
    wheel_mesh = concat_meshes(wheels).transformed(FACE_Z)
    return {"p406": {"mesh": body, "texture": livery, "scale": k,
                     "about": "TORCS's Peugeot 406 body, front towards +Z, on the ground, no wheels"},
            "p406_wheels": {"mesh": wheel_mesh, "color": [0.03, 0.03, 0.03],
                            "about": "four plain tyres where TORCS's p406.xml puts the wheels (an actor)"}}


# --- the person ------------------------------------------------------------------------------------

def _blend_parts(blend: Path, out: Path, python: Path) -> Any:
    if not python.is_file():
        raise ConvertError(f"{blend.name}: reading it needs Blender's Python ({python} not found); "
                           "run ./deploy/setup.sh without UNDREAM_SKIP_BLENDER")
    try:
        done = subprocess.run([str(python), str(HERE / "blend_parts.py"), str(blend), str(out)],
                              capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        raise ConvertError(f"{blend.name}: Blender's export did not finish in 600 s") from None
    if done.returncode or not (out / "parts.npz").is_file():
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise ConvertError(f"{blend.name}: Blender's export failed (exit {done.returncode}): {tail}")
    return np.load(out / "parts.npz")


def _part_mesh(arrays: Any, obj: str) -> Mesh:
    """One Blender object's corners as an undream mesh: canonical frame, v flipped, seams split."""
    verts, tris = arrays[f"{obj}.vertices"], arrays[f"{obj}.triangles"]
    uvs, nrms = arrays[f"{obj}.uvs"], arrays[f"{obj}.normals"]
    corners = np.c_[tris.reshape(-1, 1), uvs.reshape(-1, 2), nrms.reshape(-1, 3)]
    unique, inverse = np.unique(corners, axis=0, return_inverse=True)
    n = unique[:, 3:6] @ C
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return Mesh(verts[unique[:, 0].astype(np.int64)] @ C, inverse.reshape(-1, 3),
                np.c_[unique[:, 1], 1.0 - unique[:, 2]], n)


def _opaque(image: Image.Image) -> np.ndarray:
    """An RGBA image as opaque sRGB uint8: transparent texels take the opaque texels' mean colour."""
    rgba = np.asarray(image.convert("RGBA")).astype(np.float64) / 255.0
    a = rgba[..., 3:4]
    mean = (rgba[..., :3] * a).sum(axis=(0, 1)) / max(a.sum(), 1e-9)
    return np.round((rgba[..., :3] * a + mean * (1 - a)) * 255).astype(np.uint8)


def _baked_colour(mesh: Mesh, image: Image.Image) -> list[float]:
    """The texture's area-weighted mean (in linear light, alpha-weighted) at the triangles' UV centres,
    as sRGB in [0, 1]."""
    rgba = np.asarray(image.convert("RGBA")).astype(np.float64) / 255.0
    h, w = rgba.shape[:2]
    uv = mesh.uvs[mesh.faces].mean(axis=1) % 1.0
    texels = rgba[np.minimum((uv[:, 1] * h).astype(int), h - 1), np.minimum((uv[:, 0] * w).astype(int), w - 1)]
    weight = mesh.face_areas() * texels[:, 3]
    lin = (srgb_to_linear(texels[:, :3]) * weight[:, None]).sum(axis=0) / max(weight.sum(), 1e-12)
    return [round(float(v), 3) for v in linear_to_srgb(lin)]


def convert_person(src: Path, python: Path = BLENDER_PYTHON) -> dict[str, dict[str, Any]]:
    """``person_*`` from ``src`` (the fetched human_rig.blend): name → what to write."""
    with tempfile.TemporaryDirectory(prefix="undream-blend-") as tmp:
        arrays = _blend_parts(src / "human_rig.blend", Path(tmp), python)
        meshes = {name: _part_mesh(arrays, obj) for name, (obj, _) in PERSON_PARTS.items()}
        images = {name: Image.open(Path(tmp) / "images" / img) for name, (_, img) in PERSON_PARTS.items()}
        for im in images.values():
            im.load()
    lo = np.min([m.bounds()[0] for m in meshes.values()], axis=0)
    hi = np.max([m.bounds()[1] for m in meshes.values()], axis=0)
    k = PERSON_HEIGHT_M / (hi[1] - lo[1])
    centre = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    out: dict[str, dict[str, Any]] = {}
    for name, mesh in meshes.items():
        placed = mesh.transformed(offset=-centre).scaled(k).transformed(FACE_Z)
        entry: dict[str, Any] = {"mesh": placed, "scale": k}
        if name == "person_shirt":
            entry.update(texture=_opaque(images[name]), about="the MakeHuman man's T-shirt alone, its texture")
        else:
            entry.update(color=_baked_colour(mesh, images[name]),
                         about=f"the MakeHuman man's {name.split('_')[1]}, one colour baked from its texture (an actor)")
        out[name] = entry
    out["person_clothes"] = _clothes(out["person_shirt"]["mesh"], out["person_jeans"]["mesh"],
                                     images["person_shirt"], images["person_jeans"], k)
    return out


def _clothes(shirt: Mesh, jeans: Mesh, shirt_image: Image.Image, jeans_image: Image.Image, k: float) -> dict[str, Any]:
    """T-shirt and jeans as one mesh with one texture: an atlas 2·S wide and S tall (S:
    :data:`CLOTHES_SIDE`), the shirt's texture resampled into its left half (u ∈ [0, ½]), the jeans'
    into its right half. Their box is most of the person's (shoulders to ankles), which a detector's person box
    overlaps at IoU ≥ 0.5; the T-shirt's alone is not."""
    side = CLOTHES_SIDE
    atlas = np.concatenate([_opaque(shirt_image.resize((side, side), Image.BILINEAR)),
                            _opaque(jeans_image.resize((side, side), Image.BILINEAR))], axis=1)
    halves = [Mesh(m.vertices, m.faces, np.c_[np.clip(m.uvs[:, 0], 0, 1) / 2 + offset, np.clip(m.uvs[:, 1], 0, 1)],
                   m.normals) for m, offset in ((shirt, 0.0), (jeans, 0.5))]
    return {"mesh": concat_meshes(halves), "texture": atlas, "scale": k,
            "about": "the MakeHuman man's T-shirt and jeans, one atlas texture (shirt left, jeans right): "
                     "the attacked object"}


# --- writing ---------------------------------------------------------------------------------------

CONVERTERS: dict[str, Callable[[Path], dict[str, dict[str, Any]]]] = {
    "torcs-data": convert_car, "morse-simulator-data": convert_person}
NEEDS_BLENDER = ("morse-simulator-data",)
PRODUCES = {"torcs-data": ("p406", "p406_wheels"), "morse-simulator-data": ("person_clothes", *PERSON_PARTS)}


def _stamp(pkg: dict[str, Any]) -> dict[str, Any]:
    return {"recipe": RECIPE, "package": pkg["package"], "version": pkg["version"], "licence": pkg["licence"],
            "sources": {Path(f["to"]).name: f["sha256"] for f in pkg["files"].values()}}


def up_to_date(pkg: dict[str, Any], root: Path) -> bool:
    """True when every asset of ``pkg`` is in ``root`` and was converted from these sources by this recipe."""
    for name in PRODUCES[pkg["package"]]:
        meta = root / name / ASSET_FILE
        try:
            data = json.loads(meta.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        if {k: data.get(k) for k in _stamp(pkg)} != _stamp(pkg) or not (root / name / MESH_FILE).is_file():
            return False
        if data.get("texture") and not (root / name / TEXTURE_FILE).is_file():
            return False
    return True


def write_asset(root: Path, name: str, entry: dict[str, Any], pkg: dict[str, Any]) -> None:
    """Write one converted asset into ``root/name`` (a temporary folder moved into place)."""
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=root))
    tmp.chmod(0o755)
    try:
        mesh: Mesh = entry["mesh"]
        write_ply(mesh, tmp / MESH_FILE)
        meta = {"name": name, **_stamp(pkg), "about": entry["about"], "mesh": MESH_FILE,
                "vertices": mesh.n_vertices, "triangles": mesh.n_faces,
                "bounds_m": [np.round(b, 4).tolist() for b in mesh.bounds()]}
        if "scale" in entry:
            meta["scale"] = round(float(entry["scale"]), 6)
        if "texture" in entry:
            Image.fromarray(entry["texture"]).save(tmp / TEXTURE_FILE)
            meta["texture"] = TEXTURE_FILE
            meta["texture_size"] = list(entry["texture"].shape[1::-1])
        if "color" in entry:
            meta["color"] = entry["color"]
        (tmp / ASSET_FILE).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
        old = root / name
        if old.exists():
            shutil.rmtree(old)
        tmp.rename(old)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def convert(pkg: dict[str, Any], cache: Path) -> int:
    """Convert ``pkg``'s fetched files unless already done; the number of assets written."""
    root = assets_root(cache)
    if up_to_date(pkg, root):
        return 0
    src = cache / Path(next(iter(pkg["files"].values()))["to"]).parent
    try:
        made = CONVERTERS[pkg["package"]](src)
    except (UndreamError, OSError, KeyError, ValueError) as err:
        raise ConvertError(f"{pkg['package']} {pkg['version']}: cannot convert: {err}") from None
    for name, entry in made.items():
        write_asset(root, name, entry, pkg)
    return len(made)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=None, help="cache folder (default $XDG_CACHE_HOME/undream)")
    ap.add_argument("--check", action="store_true", help="only say what is missing; exit 1 if anything is")
    ap.add_argument("--skip-blender", action="store_true",
                    help="leave out what needs Blender's Python to convert (the person)")
    args = ap.parse_args(argv)
    cache = args.cache or default_cache()
    packages = json.loads(LOCK.read_text(encoding="utf-8"))["packages"]
    if args.skip_blender:
        for pkg in (p for p in packages if p["package"] in NEEDS_BLENDER):
            print(f"fetch_assets: {pkg['package']}: left out (--skip-blender: converting it needs Blender's Python)")
        packages = [p for p in packages if p["package"] not in NEEDS_BLENDER]
    if args.check:
        gaps = [f"{p['package']}: {src}" for p in packages for src in missing(p, cache)]
        gaps += [f"{p['package']}: not converted" for p in packages if not up_to_date(p, assets_root(cache))]
        print("\n".join(gaps) or f"fetch_assets: everything is in {assets_root(cache)}")
        return 1 if gaps else 0
    try:
        for pkg in packages:
            fetched = fetch(pkg, cache)
            made = convert(pkg, cache)
            print(f"fetch_assets: {pkg['package']} {pkg['version']}: "
                  f"{f'{fetched} file(s) fetched' if fetched else 'sources in the cache'}, "
                  f"{f'{made} asset(s) converted' if made else 'assets up to date'} "
                  f"({', '.join(PRODUCES[pkg['package']])})")
    except (FetchError, OSError, StopIteration) as err:
        print(f"fetch_assets: error: {err or 'the download left no archive'}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
