"""Triangle meshes with UVs: a validated container, PLY I/O and user-file loading.

Conventions (Mitsuba's, verified against Mitsuba 3.9.1):

- Positions in metres, right-handed, Y up. Faces are counter-clockwise seen
  from outside, so the right-hand rule gives outward normals.
- UVs are exactly the values Mitsuba stores in ``vertex_texcoords`` and its
  ``bitmap`` texture looks up: ``u`` runs along texel columns (left to right)
  and ``v`` runs along texel **rows, downwards**: row 0 (the top row of the
  image file or of the ``H×W×3`` array) is at ``v = 0``. Texel ``(row, col)``
  of an ``H×W`` texture covers ``u ∈ [col/W, (col+1)/W)``,
  ``v ∈ [row/H, (row+1)/H)`` (see :func:`uv_to_texel`). OBJ files store
  ``vt`` with v up; Mitsuba's OBJ loader flips them (``v → 1 − v``) on load,
  and :func:`load_mesh_file` returns the flipped values the renderer uses.
  PLY texcoords are used as stored (no flip).

Only numpy is imported here; :func:`write_ply` (Mitsuba's own PLY writer) and
:func:`load_mesh_file` (Mitsuba's loaders) import Mitsuba lazily. :func:`read_ply`
stays plain numpy so that tests check what was written independently of Mitsuba.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from undream.errors import AssetError
from undream.spec.io import naming
from undream.variant import mitsuba

MESH_SUFFIXES = (".obj", ".ply")
_PLY_POS = ("x", "y", "z")
_PLY_NRM = ("nx", "ny", "nz")
_PLY_UVS = (("s", "t"), ("u", "v"))  # Mitsuba writes s/t; its loader also reads u/v, texture_u/v


def _array(name: str, value: object, dtype: type, cols: int) -> np.ndarray:
    arr = np.ascontiguousarray(value, dtype=dtype)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise AssetError(f"{name}: expected shape (n, {cols}), got {arr.shape}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise AssetError(f"{name}: contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


def _faces(value: object, n: int) -> np.ndarray:
    raw = np.asarray(value)
    if raw.size and raw.dtype.kind not in "iu":
        raise AssetError(f"faces: must be integer vertex indices, got dtype {raw.dtype}")
    f = _array("faces", raw, np.int64, 3)
    if len(f) and (f.min() < 0 or f.max() >= n):
        raise AssetError(f"faces: vertex indices must be in [0, {n}), got "
                         f"[{int(f.min())}, {int(f.max())}]")
    return _array("faces", f, np.int32, 3)


def _per_vertex(name: str, value: object, cols: int, n: int, what: str) -> np.ndarray:
    arr = _array(name, value, np.float32, cols)
    if len(arr) != n:
        raise AssetError(f"{name}: expected one {what} per vertex ({n}), got {len(arr)}")
    return arr


@dataclass(frozen=True, eq=False)
class Mesh:
    """An indexed triangle mesh with one UV per vertex.

    ``vertices`` float32 (N, 3) metres; ``faces`` int32 (M, 3) vertex indices,
    counter-clockwise seen from outside; ``uvs`` float32 (N, 2) in [0, 1]
    (Mitsuba's convention, v down along texel rows, see the module docstring);
    ``normals`` float32 (N, 3) unit vectors or ``None``. Arrays are read-only.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = _array("vertices", self.vertices, np.float32, 3)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", _faces(self.faces, len(v)))
        object.__setattr__(self, "uvs", _per_vertex("uvs", self.uvs, 2, len(v), "UV"))
        if self.normals is not None:
            nrm = _per_vertex("normals", self.normals, 3, len(v), "normal")
            object.__setattr__(self, "normals", nrm)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Mesh):
            return NotImplemented
        same_n = (self.normals is None) == (other.normals is None)
        return (same_n and np.array_equal(self.vertices, other.vertices)
                and np.array_equal(self.faces, other.faces) and np.array_equal(self.uvs, other.uvs)
                and (self.normals is None or np.array_equal(self.normals, other.normals)))

    __hash__ = None  # type: ignore[assignment]

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def scaled(self, s: float) -> "Mesh":
        """Uniformly scaled by ``s`` > 0 about the origin (normals and UVs unchanged)."""
        if not np.isfinite(s) or s <= 0:
            raise AssetError(f"scale: must be a finite number > 0, got {s!r}")
        return Mesh(self.vertices * np.float32(s), self.faces, self.uvs, self.normals)

    def transformed(self, rotation: np.ndarray | None = None,
                    offset: Sequence[float] = (0.0, 0.0, 0.0)) -> "Mesh":
        """``p → R @ p + offset`` for a proper rotation ``R`` (3×3; winding is kept)."""
        r = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        v = self.vertices.astype(np.float64) @ r.T + np.asarray(offset, dtype=np.float64)
        n = None if self.normals is None else self.normals.astype(np.float64) @ r.T
        return Mesh(v, self.faces, self.uvs, n)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min_xyz, max_xyz)`` in metres (float64)."""
        v = self.vertices.astype(np.float64)
        return v.min(axis=0), v.max(axis=0)

    def face_areas(self) -> np.ndarray:
        """Area of each triangle in m² (float64, shape (M,))."""
        return 0.5 * np.linalg.norm(_face_cross(self.vertices, self.faces), axis=1)

    def surface_area(self) -> float:
        """Total area in m²."""
        return float(self.face_areas().sum())

    def face_normals(self) -> np.ndarray:
        """Unit normals from the winding (right-hand rule), float64 (M, 3)."""
        c = _face_cross(self.vertices, self.faces)
        return c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-300)


def _face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = vertices.astype(np.float64)[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def concat_meshes(meshes: Sequence[Mesh]) -> Mesh:
    """One mesh holding all of ``meshes`` (normals kept only if every part has them)."""
    if not meshes:
        raise AssetError("concat_meshes: needs at least one mesh")
    offsets = np.cumsum([0] + [m.n_vertices for m in meshes[:-1]])
    faces = np.concatenate([m.faces.astype(np.int64) + o for m, o in zip(meshes, offsets)])
    normals = None
    if all(m.normals is not None for m in meshes):
        normals = np.concatenate([m.normals for m in meshes])  # type: ignore[misc]
    return Mesh(np.concatenate([m.vertices for m in meshes]), faces,
                np.concatenate([m.uvs for m in meshes]), normals)


def uv_to_texel(uv: np.ndarray, height: int, width: int) -> np.ndarray:
    """Continuous texel coordinates ``(row, col)`` of UVs, as Mitsuba's bitmap samples them.

    Texel centres sit at integers: ``row = v·H − ½``, ``col = u·W − ½``
    (row 0 is the first row of the ``H×W×3`` texture array, at v = 0).
    """
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([uv[..., 1] * height - 0.5, uv[..., 0] * width - 0.5], axis=-1)


# --- PLY -------------------------------------------------------------------------------------

def write_ply(mesh: Mesh, path: str | Path) -> Path:
    """Write ``mesh`` as PLY with Mitsuba's own writer (``mi.Mesh.write_ply``); returns the path.

    Binary little-endian; vertex properties ``x y z [nx ny nz] s t`` (float32;
    normals only when the mesh has them), faces ``list uchar int
    vertex_indices``. UVs are written as stored (Mitsuba does not flip PLY
    texcoords). Uses the process's Mitsuba variant (see :mod:`undream.variant`).
    """
    path = Path(path)
    mi = mitsuba()
    shape = mi.Mesh("mesh", mesh.n_vertices, mesh.n_faces, has_vertex_normals=mesh.normals is not None,
                    has_vertex_texcoords=True)
    params = mi.traverse(shape)
    buffers = {"vertex_positions": mesh.vertices, "faces": mesh.faces.astype(np.uint32),
               "vertex_texcoords": mesh.uvs, "vertex_normals": mesh.normals}
    for key, array in buffers.items():
        if array is not None:
            params[key] = type(params[key])(array.ravel())  # the variant's own buffer type
    params.update()
    with naming(path):  # Mitsuba's RuntimeError on a full disk: an OSError naming the file
        shape.write_ply(str(path))
    return path


def _parse_ply_header(path: Path, blob: bytes) -> tuple[list[str], int, int, int]:
    end = blob.find(b"end_header\n")
    if not blob.startswith(b"ply\n") or end < 0:
        raise AssetError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    lines = blob[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise AssetError(f"{path}: read_ply only reads binary_little_endian PLY files such as write_ply writes")
    props: list[str] = []
    counts = {"vertex": -1, "face": -1}
    element = ""
    for line in lines:
        tok = line.split()
        if tok[:1] == ["element"] and len(tok) == 3:
            element, counts[tok[1]] = tok[1], int(tok[2])
        elif tok[:2] == ["property", "float"] and element == "vertex":
            props.append(tok[2])
        elif tok[:1] == ["property"] and tok != "property list uchar int vertex_indices".split():
            raise AssetError(f"{path}: unsupported PLY property {line.strip()!r} (write_ply format only)")
    return props, counts["vertex"], counts["face"], end + len(b"end_header\n")


def read_ply(path: str | Path) -> Mesh:
    """Read a PLY written by :func:`write_ply` back into an identical :class:`Mesh`.

    Pure numpy (no Mitsuba), so independent code can check what was written;
    it reads binary little-endian float vertices ``x y z [nx ny nz]`` followed
    by ``s t`` or ``u v``, and triangle faces.
    """
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: file not found")
    blob = path.read_bytes()
    props, nv, nf, start = _parse_ply_header(path, blob)
    has_n = all(p in props for p in _PLY_NRM)
    wanted = [list(_PLY_POS + (_PLY_NRM if has_n else ()) + uv) for uv in _PLY_UVS]
    if props not in wanted or nv < 0 or nf < 0:
        raise AssetError(f"{path}: expected vertex properties {' '.join(wanted[0])}, got {' '.join(props)}")
    vbytes, fdt = nv * len(props) * 4, np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    if len(blob) != start + vbytes + nf * fdt.itemsize:
        raise AssetError(f"{path}: truncated or not triangles only (size {len(blob)} bytes)")
    vdata = np.frombuffer(blob, "<f4", nv * len(props), start).reshape(nv, len(props))
    fdata = np.frombuffer(blob, fdt, nf, start + vbytes)
    if nf and (fdata["n"] != 3).any():
        raise AssetError(f"{path}: only triangle faces are supported")
    normals = vdata[:, 3:6] if has_n else None
    return Mesh(vdata[:, :3], fdata["i"], vdata[:, -2:], normals)


# --- user files, through Mitsuba's own loaders ------------------------------------------------

def _mitsuba_reason(err: Exception) -> str:
    """Mitsuba's one-line reason, without source locations and parser context."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    text = re.sub(r"\[[\w./\\-]+:\d+\]\s*", "", text)
    m = re.search(r"Error while loading \w+ file \"[^\"]*\":\s*(.*)", text)
    if m:
        text = m.group(1)
    return re.sub(r"^\"[^\"]*\":\s*", "", text).strip() or type(err).__name__


def load_mesh_file(path: str | Path) -> Mesh:
    """Load an OBJ or PLY file with Mitsuba's own loader and return what the renderer sees.

    Vertices are Mitsuba's (OBJ corners deduplicated per position/UV/normal
    triple), UVs are Mitsuba's (OBJ ``vt`` flipped to v down), normals are the
    file's or those Mitsuba computes. Raises :class:`AssetError` (one line)
    when the file is missing, has another extension, cannot be parsed or has
    no UV coordinates.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise AssetError(f"{path}: unsupported mesh extension {path.suffix!r} (valid: .obj, .ply)")
    if not path.is_file():
        raise AssetError(f"{path}: file not found")
    mi = mitsuba()
    try:
        shape = mi.load_dict({"type": suffix[1:], "filename": str(path.resolve())})
    except Exception as err:  # Mitsuba raises plain RuntimeError with multi-line context
        raise AssetError(f"{path}: Mitsuba cannot load this mesh: {_mitsuba_reason(err)}") from None
    if not shape.has_vertex_texcoords():
        raise AssetError(f"{path}: mesh has no UV coordinates (texcoords); undream needs a "
                         "UV-mapped mesh to place the adversarial texture")
    normals = None
    if shape.has_vertex_normals():
        normals = np.array(shape.vertex_normals_buffer(), dtype=np.float32).reshape(-1, 3)
    return Mesh(np.array(shape.vertex_positions_buffer(), dtype=np.float32).reshape(-1, 3),
                np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3),
                np.array(shape.vertex_texcoords_buffer(), dtype=np.float32).reshape(-1, 2),
                normals)
