"""Import a Blender scene (``.blend``: an animated camera and a named, UV-mapped object) as a canonical sequence.

``undream init scene.blend --object NAME [--camera NAME] --out DIR`` (or
:func:`sequence_from_blend`). Blender runs in its own interpreter
(:mod:`undream.bridge.blender_python`): :mod:`undream.bridge.blender_export`
writes Blender's values as JSON, and this module validates and converts them.
The export format, version 1 (Blender's world: right-handed, Z up, metres)::

    {"format": "undream-blender-export", "version": 1, "blend": PATH, "blender": "5.0.1",
     "scene": "Scene", "fps": 24.0, "resolution": [W, H], "pixel_aspect": [1, 1],
     "camera": {"name": "Camera"},
     "object": {"name": "Crate", "mesh": {"vertices": [[x, y, z], ...],      # object-local
                                           "triangles": [[i, j, k], ...],    # vertex indices
                                           "uvs": [[[u, v] × 3], ...],       # per corner, v up
                                           "normals": [[[x, y, z] × 3], ...]}},
     "actors": [{"name": "Walker", "mesh": {...}}, ...],               # --actor objects (UVs (0, 0) if none)
     "frames": [{"frame": 1,
                 "camera": {"matrix_world": 4×4, "view_frame": [[x, y, z] × 4]},
                 "object": {"matrix_world": 4×4},
                 "actors": {"Walker": {"matrix_world": 4×4}, ...}}, ...]}

Conversion, matrices only (no Euler angles): a Blender point ``p_b`` is the
canonical point ``Cᵀ p_b`` with ``C = [[1,0,0],[0,0,-1],[0,1,0]]`` (canonical
y is Blender's z, canonical z is Blender's −y), the inverse of
:mod:`undream.sim.blender_scene`'s mapping. The object keeps its up: its
mesh becomes ``Cᵀ v`` (Blender's local +Z is the mesh's +Y) and its pose
``Cᵀ·W·C``. Blender's camera looks along its local −Z with +X to the right,
Mitsuba's along +Z with +X to the left: the camera pose is ``Cᵀ·W·diag(−1, 1, −1)``
with any scale divided out. The horizontal field of view comes from the view
frame, so the sensor fit (auto, horizontal, vertical), lens and sensor size
are Blender's. UV ``v`` is flipped (``1 − v``: Mitsuba's runs down the rows).
Frame indices are Blender's frame numbers (``frame_start`` to ``frame_end``,
every ``frame_step``), times ``(frame − frame_start) / fps``.

Objects named as actors (``--actor NAME``: occluders, other traffic; UVs
optional) come with their meshes and poses, converted like the object's, in
undream's default grey. Not imported: lights, world, materials, other
objects (the environment is undream's, :class:`~undream.spec.Environment`),
lens shift, non-square pixels, orthographic or panoramic cameras (refused
with one line), and mesh deformation over time (a mesh is the first
frame's; its pose follows every frame). Meshes are written as PLY files into
a content-addressed cache (``$XDG_CACHE_HOME/undream/blend``) that the
sequence's assets name; ``undream init`` copies them into the scene
directory like any mesh.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import subprocess
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from undream.bridge.blender_python import HINT, blender_env, blender_python, bpy_problem, import_root
from undream.errors import BridgeError, SpecError
from undream.spec import ActorPose, Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec import _check
from undream.spec.io import atomic_write

FORMAT = "undream-blender-export"
VERSION = 1
C = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # canonical → Blender; Blender → canonical is C.T
C4 = np.eye(4)
C4[:3, :3] = C
CAMERA_FLIP = np.diag([-1.0, 1.0, -1.0, 1.0])
EXPORT_TIMEOUT_S = 600


@dataclass(frozen=True)
class BlendSource:
    """A ``.blend`` file and what to take from it: the adversarial ``object`` (a mesh object's name),
    the ``camera`` (an object's name; None: the scene's active camera) and extra ``actors`` (mesh
    objects' names: occluders, other traffic; UVs optional)."""

    path: Path
    object: str
    camera: str | None = None
    actors: tuple[str, ...] = ()
    # How to run Blender, from the edge (undream.settings.LocalSettings): its interpreter (None: the
    # default), where the object's mesh is cached (None: ~/.cache/undream/blend) and the environment
    # its process gets (None: only what undream sets). Not part of what the source is.
    python: str | None = field(default=None, compare=False)
    cache_dir: str | None = field(default=None, compare=False)
    env: Mapping[str, str] | None = field(default=None, repr=False, compare=False)

    def __str__(self) -> str:
        return str(self.path)

    def describe(self) -> str:
        """What ``metadata.json`` records as the spec."""
        return json.dumps({"blend": str(Path(self.path).resolve()), "object": self.object, "camera": self.camera,
                           "actors": list(self.actors)})


@dataclass(frozen=True)
class BlendMesh:
    """The object's mesh in the canonical local frame: float (N,3) vertices, int (M,3) faces,
    (N,2) UVs (Mitsuba's, v down), (N,3) unit normals."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    normals: np.ndarray


def sequence_from_blend(source: BlendSource, texture: TextureParam | None = None,
                        environment: Environment | None = None, python: str | Path | None = None,
                        cache_dir: str | Path | None = None, env: Mapping[str, str] | None = None) -> Sequence:
    """Read ``source`` with Blender's Python and return its canonical sequence (see the module docstring).

    Every error is one :class:`BridgeError` line naming the file: no Blender
    Python, no such object or camera, an object without UVs, a camera undream
    cannot reproduce. The object's mesh is written to ``cache_dir`` (default
    ``source.cache_dir``, else ``~/.cache/undream/blend``; the edge passes
    ``$XDG_CACHE_HOME/undream/blend``) only once everything checked out.
    ``python`` and ``env``: Blender's interpreter and its environment (default
    ``source``'s, see :func:`run_export`).
    """
    path = Path(source.path)
    if not path.is_file():
        raise BridgeError(f"{path}: file not found")
    data = run_export(source, python, env)
    try:
        seq, meshes = sequence_from_export(data, texture, environment, name=path.stem)
    except (BridgeError, SpecError) as err:
        raise BridgeError(" ".join(f"{path}: {err}".split())) from None
    cache_dir = cache_dir or source.cache_dir
    cache = Path(cache_dir) if cache_dir else Path.home() / ".cache" / "undream" / "blend"
    files = {name: str(write_cached_ply(mesh, cache)) for name, mesh in meshes.items()}
    return replace(seq, asset=replace(seq.asset, mesh=files[seq.asset.name]),
                   actors=tuple(replace(a, mesh=files[a.name]) for a in seq.actors))


def run_export(source: BlendSource, python: str | Path | None = None,
               env: Mapping[str, str] | None = None) -> Mapping[str, Any]:
    """Run :mod:`undream.bridge.blender_export` on ``source`` in Blender's interpreter; its JSON.

    ``python``: the interpreter (default ``source.python``, else :func:`blender_python`'s default);
    ``env``: its environment (default ``source.env``; see :func:`blender_env`)."""
    path = Path(source.path)
    python = blender_python(python or source.python)
    env = env if env is not None else source.env
    problem = bpy_problem(python)
    if problem is not None:
        kind, reason = problem
        what = f"{reason} not found" if kind == "missing" else f"{python} cannot import bpy ({reason})"
        raise BridgeError(f"{path}: reading a .blend needs Blender's Python (bpy 5.0.1): {what}; {HINT}")
    root = import_root()
    try:
        out = root / "export.json"
        cmd = [str(python), "-m", "undream.bridge.blender_export", str(path.resolve()), "--object", source.object,
               "--out", str(out)] + (["--camera", source.camera] if source.camera else [])
        for actor in source.actors:
            cmd += ["--actor", actor]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, env=blender_env(root, env), cwd=str(root),
                                  timeout=EXPORT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise BridgeError(f"{path}: Blender did not finish the export in {EXPORT_TIMEOUT_S} s") from None
        if not out.is_file():
            last = (proc.stderr.strip().splitlines() or ["no output"])[-1][:300]
            raise BridgeError(f"{path}: Blender's export ended without a result (exit code {proc.returncode}; "
                              f"last output: {last})")
        data = json.loads(out.read_text())
    finally:
        shutil.rmtree(root, ignore_errors=True)
    if "error" in data:
        raise BridgeError(" ".join(f"{path}: {data['error']}".split()))
    return data


# --- validation and conversion (no Blender needed) ------------------------------------------------

def _array(value: Any, where: str, shape: tuple[int | None, ...], dtype: type = float) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        raise BridgeError(f"{where}: must be an array of shape {_shape(shape)}") from None
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise BridgeError(f"{where}: must be an array of shape {_shape(shape)}, got {list(arr.shape)}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise BridgeError(f"{where}: must be finite numbers")
    return arr


def _shape(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"


def _fields(value: Any, where: str, required: tuple[str, ...]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise BridgeError(f"{where or 'export'}: must be a JSON object")
    for k in required:
        if k not in value:
            raise BridgeError(f"{where + '.' if where else ''}{k}: is required")
    return value


def sequence_from_export(data: Any, texture: TextureParam | None = None, environment: Environment | None = None,
                         name: str = "blend") -> tuple[Sequence, dict[str, BlendMesh]]:
    """The canonical sequence of an export (its assets' meshes placeholder paths) and the meshes by asset name."""
    d = _fields(data, "", ("format", "version", "fps", "resolution", "pixel_aspect", "object", "frames"))
    if d["format"] != FORMAT or d["version"] != VERSION:
        raise BridgeError(f"format: must be {FORMAT!r} version {VERSION}, got {d['format']!r} {d['version']!r}")
    fps = _check.positive("fps", d["fps"])
    res = _check.ints("resolution", d["resolution"], 2, 1, 16384)
    aspect = _array(d["pixel_aspect"], "pixel_aspect", (2,))
    if abs(aspect[0] - aspect[1]) > 1e-6 * max(aspect):
        raise BridgeError(f"pixel_aspect: undream needs square pixels, got {aspect.tolist()}")
    obj = _fields(d["object"], "object", ("name", "mesh"))
    asset = Asset(_safe_name(str(obj["name"]), "object"), "blend-mesh.ply", texture=texture or TextureParam())
    meshes = {asset.name: _mesh(obj["mesh"], "object.mesh")}
    actors_raw = d.get("actors", [])
    if not isinstance(actors_raw, list):
        raise BridgeError("actors: must be a list")
    labels: dict[str, str] = {}  # Blender name → asset name
    for i, a in enumerate(actors_raw):
        a = _fields(a, f"actors[{i}]", ("name", "mesh"))
        labels[str(a["name"])] = _safe_name(str(a["name"]), f"actor{i}")
        meshes[labels[str(a["name"])]] = _mesh(a["mesh"], f"actors[{i}].mesh")
    frames_raw = d["frames"]
    if not isinstance(frames_raw, list) or not frames_raw:
        raise BridgeError("frames: the scene's frame range holds no frame")
    start = frames_raw[0].get("frame", 0) if isinstance(frames_raw[0], Mapping) else 0
    frames = tuple(_frame(f, f"frames[{i}]", res, fps, start, environment or Environment(), labels)
                   for i, f in enumerate(frames_raw))
    actors = tuple(Asset(n, "blend-mesh.ply") for n in labels.values())
    seq = Sequence(name=_safe_name(name, "blend"), asset=asset, frames=frames, actors=actors, fps=fps,
                   source="blender")
    return seq, meshes


def _safe_name(name: str, fallback: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", name) or fallback


def _mesh(value: Any, where: str) -> BlendMesh:
    m = _fields(value, where, ("vertices", "triangles", "uvs", "normals"))
    verts = _array(m["vertices"], f"{where}.vertices", (None, 3))
    tris = _array(m["triangles"], f"{where}.triangles", (None, 3), np.int64)
    n = len(tris)
    uvs = _array(m["uvs"], f"{where}.uvs", (n, 3, 2))
    normals = _array(m["normals"], f"{where}.normals", (n, 3, 3))
    if n == 0:
        raise BridgeError(f"{where}: has no faces")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise BridgeError(f"{where}.triangles: vertex indices must be in [0, {len(verts)})")
    # One undream vertex per distinct (Blender vertex, UV, normal) corner: UV seams and hard edges split.
    corners = np.c_[tris.reshape(-1, 1), uvs.reshape(-1, 2), normals.reshape(-1, 3)]
    unique, inverse = np.unique(corners, axis=0, return_inverse=True)
    vi = unique[:, 0].astype(np.int64)
    nrm = unique[:, 3:6] @ C  # (Cᵀ n)ᵀ = nᵀ C
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(length > 1e-12, nrm / np.maximum(length, 1e-12), [0.0, 1.0, 0.0])
    uv = np.c_[unique[:, 1], 1.0 - unique[:, 2]]
    return BlendMesh(verts[vi] @ C, inverse.reshape(-1, 3), uv, nrm)


def _matrix(value: Any, where: str) -> np.ndarray:
    m = _array(value, where, (4, 4))
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise BridgeError(f"{where}: must be an affine matrix (last row 0 0 0 1)")
    return m


def _frame(value: Any, where: str, res: tuple[int, int], fps: float, start: int, env: Environment,
           labels: Mapping[str, str]) -> Frame:
    f = _fields(value, where, ("frame", "camera", "object"))
    number = f["frame"]
    if isinstance(number, bool) or not isinstance(number, int) or number < 0:
        raise BridgeError(f"{where}.frame: must be a frame number >= 0 (undream keeps Blender's numbers), "
                          f"got {number!r}")
    cam = _fields(f["camera"], f"{where}.camera", ("matrix_world", "view_frame"))
    obj = _fields(f["object"], f"{where}.object", ("matrix_world",))
    actors = f.get("actors", {})
    if not isinstance(actors, Mapping) or set(actors) != set(labels):
        raise BridgeError(f"{where}.actors: must hold the matrix of every actor ({', '.join(labels) or 'none'})")
    with _check.at(where, catch=(BridgeError, SpecError), raise_as=BridgeError):
        camera = _camera(cam, res)
        pose = C4.T @ _matrix(obj["matrix_world"], "object.matrix_world") @ C4
        poses = tuple(ActorPose(labels[k], Transform.from_rows(
            C4.T @ _matrix(_fields(actors[k], f"actors.{k}", ("matrix_world",))["matrix_world"],
                           f"actors.{k}.matrix_world") @ C4)) for k in labels)
        return Frame(index=number, camera=camera, object_to_world=Transform.from_rows(pose), environment=env,
                     actors=poses, time=(number - start) / fps)


def _camera(cam: Mapping[str, Any], res: tuple[int, int]) -> Camera:
    m = C4.T @ _matrix(cam["matrix_world"], "camera.matrix_world") @ CAMERA_FLIP
    lengths = np.linalg.norm(m[:3, :3], axis=0)
    if lengths.min() < 1e-9:
        raise BridgeError("camera.matrix_world: the camera is scaled to zero")
    m[:3, :3] /= lengths
    r = m[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
        raise BridgeError("camera.matrix_world: the camera is sheared or mirrored (undream needs a rigid camera)")
    u, _, vt = np.linalg.svd(r)  # the nearest rotation (removes float noise)
    m[:3, :3] = u @ vt
    corners = _array(cam["view_frame"], "camera.view_frame", (4, 3))
    depth = -corners[:, 2]
    if depth.min() <= 0 or np.ptp(depth) > 1e-6 * depth.max():
        raise BridgeError("camera.view_frame: must be a rectangle in front of the camera")
    x0, x1, y0, y1 = corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max()
    if abs(x0 + x1) > 1e-5 * (x1 - x0) or abs(y0 + y1) > 1e-5 * (y1 - y0):
        raise BridgeError("camera: lens shift is not supported (set shift x and y to 0)")
    w, h = res
    if abs((x1 - x0) / (y1 - y0) - w / h) > 1e-3 * w / h:
        raise BridgeError(f"camera.view_frame: aspect {(x1 - x0) / (y1 - y0):.4f} is not the resolution's {w / h:.4f}")
    fov = math.degrees(2.0 * math.atan(x1 / depth.mean()))
    return Camera(Transform.from_rows(m), fov, res)


# --- the mesh file --------------------------------------------------------------------------------

def ply_bytes(mesh: BlendMesh) -> bytes:
    """Binary little-endian PLY (``x y z nx ny nz s t``, triangles), as Mitsuba and ``read_ply`` read it."""
    n, m = len(mesh.vertices), len(mesh.faces)
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in "x y z nx ny nz s t".split())
            + f"element face {m}\nproperty list uchar int vertex_indices\nend_header\n").encode("ascii")
    verts = np.c_[mesh.vertices, mesh.normals, mesh.uvs].astype("<f4")
    faces = np.zeros(m, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, mesh.faces
    return head + verts.tobytes() + faces.tobytes()


def write_cached_ply(mesh: BlendMesh, cache: Path) -> Path:
    """Write ``mesh`` as ``cache/<sha256 prefix>.ply`` (once; atomically) and return its path."""
    blob = ply_bytes(mesh)
    path = cache / f"{hashlib.sha256(blob).hexdigest()[:24]}.ply"
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        atomic_write(path, blob, mode=0o600)
    return path

