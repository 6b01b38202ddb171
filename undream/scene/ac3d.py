"""AC3D model files (``.ac``, and TORCS's ``.acc`` variant) as one UV-mapped :class:`Mesh`.

What is read: ``OBJECT`` blocks (nested through ``kids``) with ``name``,
``texture`` (the first one is the base texture; TORCS's ``.acc`` lists up to
four, each ``refs`` line then carries one UV pair per texture, the base pair
first), ``texrep``/``texoff`` (applied to the UVs), ``rot`` (3×3, row-major)
and ``loc`` (an object's vertices and its kids are placed by ``rot`` then
``loc`` in its parent's frame), ``numvert`` (``x y z``, or ``x y z nx ny nz``
in ``.acc`` files) and ``numsurf`` with ``SURF`` blocks: polygons (type 0,
fan-triangulated) and TORCS's triangle strips (type 4); lines (types 1, 2) are
skipped. ``MATERIAL`` lines, ``data``, ``url`` and ``crease`` are ignored
(the attacked texture replaces the material).

Conventions: AC3D is right-handed, Y up, in the model's units (TORCS: metres,
the car's length along X) — undream's canonical frame, so positions are kept.
AC3D's ``v`` runs up the image (OpenGL); undream's runs down the rows
(:mod:`undream.scene.mesh`), so ``v → 1 − v``. Triangles are wound
counter-clockwise seen along the file's vertex normals where it has them
(strips alternate their winding; TORCS's surfaces are two-sided), and
degenerate triangles (a repeated vertex, as strips use to join) are dropped.
One undream vertex per distinct (file vertex, UV) pair. Only numpy.
"""
from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from undream.errors import AssetError
from undream.scene.mesh import Mesh

SURF_POLYGON, SURF_STRIP = 0, 4
_LINES = (1, 2)


@dataclass
class Ac3dPart:
    """One ``OBJECT`` with surfaces: its vertices in the model's frame (float64 (N, 3), after every
    enclosing ``rot``/``loc``), normals (N, 3) or None, and triangles as (file vertex, u, v) corners."""

    name: str
    texture: str | None
    vertices: np.ndarray
    normals: np.ndarray | None
    corners: list[tuple[int, float, float]] = field(default_factory=list)  # 3 per triangle, v up


class _Lines:
    def __init__(self, text: str, where: str) -> None:
        self.lines = text.splitlines()
        self.i = 0
        self.where = where

    def next(self) -> list[str]:
        while self.i < len(self.lines):
            line = self.lines[self.i].strip()
            self.i += 1
            if line:
                try:
                    return shlex.split(line)
                except ValueError:
                    raise self.error(f"cannot split {line[:60]!r}") from None
        raise AssetError(f"{self.where}: ends early (after line {self.i})")

    def error(self, what: str) -> AssetError:
        return AssetError(f"{self.where}: line {self.i}: {what}")

    def numbers(self, tok: list[str], n: int | None, what: str) -> list[float]:
        try:
            vals = [float(t) for t in tok]
        except ValueError:
            raise self.error(f"{what}: expected numbers, got {' '.join(tok)[:60]!r}") from None
        if n is not None and len(vals) != n:
            raise self.error(f"{what}: expected {n} numbers, got {len(vals)}")
        if not np.isfinite(vals).all():
            raise self.error(f"{what}: numbers must be finite")
        return vals


def _count(lines: _Lines, tok: list[str], what: str) -> int:
    if len(tok) != 2 or not tok[1].isdigit():
        raise lines.error(f"{what}: expected '{what} N', got {' '.join(tok)[:60]!r}")
    return int(tok[1])


def _surface(lines: _Lines, tok: list[str], n_vert: int) -> tuple[int, list[tuple[int, float, float]]]:
    try:
        kind = int(tok[1], 0) & 0xF
    except (IndexError, ValueError):
        raise lines.error(f"SURF: expected 'SURF 0xNN', got {' '.join(tok)[:60]!r}") from None
    tok = lines.next()
    if tok[0] == "mat":
        tok = lines.next()
    if tok[0] != "refs":
        raise lines.error(f"SURF: expected 'refs N', got {' '.join(tok)[:60]!r}")
    refs = []
    for _ in range(_count(lines, tok, "refs")):
        vals = lines.numbers(lines.next(), None, "refs")
        if len(vals) < 3:
            raise lines.error(f"refs: expected a vertex index and a UV pair, got {len(vals)} number(s)")
        idx = int(vals[0])
        if idx != vals[0] or not 0 <= idx < n_vert:
            raise lines.error(f"refs: vertex index {vals[0]:g} not in [0, {n_vert})")
        refs.append((idx, vals[1], vals[2]))
    return kind, refs


def _triangles(kind: int, refs: list[tuple[int, float, float]]) -> list[tuple[tuple[int, float, float], ...]]:
    if kind == SURF_POLYGON:
        return [(refs[0], refs[k], refs[k + 1]) for k in range(1, len(refs) - 1)]
    return [(refs[k], refs[k + 1], refs[k + 2]) if k % 2 == 0 else (refs[k + 1], refs[k], refs[k + 2])
            for k in range(len(refs) - 2)]


def _object(lines: _Lines, tok: list[str], parent: np.ndarray, parts: list[Ac3dPart]) -> None:
    """Read one ``OBJECT`` (``tok`` is its first line) and its kids into ``parts``."""
    name, texture = "", None
    rot, loc, rep, off = np.eye(3), np.zeros(3), np.ones(2), np.zeros(2)
    verts = np.zeros((0, 3))
    normals: np.ndarray | None = None
    corners: list[tuple[int, float, float]] = []
    while True:
        tok = lines.next()
        key = tok[0]
        if key == "name":
            name = tok[1] if len(tok) > 1 else ""
        elif key == "data":
            lines.i += 1  # the data string's line
        elif key == "texture":
            texture = texture or (tok[1] if len(tok) > 1 else None)
        elif key == "texrep":
            rep = np.array(lines.numbers(tok[1:], 2, "texrep"))
        elif key == "texoff":
            off = np.array(lines.numbers(tok[1:], 2, "texoff"))
        elif key == "rot":
            rot = np.array(lines.numbers(tok[1:], 9, "rot")).reshape(3, 3)
        elif key == "loc":
            loc = np.array(lines.numbers(tok[1:], 3, "loc"))
        elif key == "numvert":
            rows = [lines.numbers(lines.next(), None, "numvert") for _ in range(_count(lines, tok, "numvert"))]
            if any(len(r) not in (3, 6) for r in rows):
                raise lines.error("numvert: each vertex is 'x y z' or 'x y z nx ny nz'")
            arr = np.array(rows, dtype=np.float64).reshape(-1, len(rows[0]) if rows else 3)
            verts = arr[:, :3]
            normals = arr[:, 3:6] if arr.shape[1] == 6 and all(len(r) == 6 for r in rows) else None
        elif key == "numsurf":
            for _ in range(_count(lines, tok, "numsurf")):
                head = lines.next()
                if head[0] != "SURF":
                    raise lines.error(f"expected 'SURF', got {' '.join(head)[:60]!r}")
                kind, refs = _surface(lines, head, len(verts))
                if kind in _LINES:
                    continue
                if kind not in (SURF_POLYGON, SURF_STRIP):
                    raise lines.error(f"SURF: unknown surface type {kind} (valid: 0 polygon, 1–2 lines, 4 strip)")
                for tri in _triangles(kind, refs):
                    if len({c[0] for c in tri}) == 3:
                        corners.extend((i, u * rep[0] + off[0], v * rep[1] + off[1]) for i, u, v in tri)
        elif key == "kids":
            to_parent = np.eye(4)
            to_parent[:3, :3], to_parent[:3, 3] = rot, loc
            world = parent @ to_parent
            if corners:
                pos = verts @ world[:3, :3].T + world[:3, 3]
                nrm = None if normals is None else normals @ np.linalg.inv(world[:3, :3])
                parts.append(Ac3dPart(name, texture, pos, nrm, corners))
            for _ in range(_count(lines, tok, "kids")):
                child = lines.next()
                if child[0] != "OBJECT":
                    raise lines.error(f"expected 'OBJECT', got {' '.join(child)[:60]!r}")
                _object(lines, child, world, parts)
            return
        elif key in ("url", "crease", "MATERIAL", "subdiv", "hidden", "locked", "folded"):
            pass
        else:
            raise lines.error(f"unknown AC3D token {key!r}")


def read_ac3d(path: str | Path) -> list[Ac3dPart]:
    """The parts (``OBJECT`` blocks with surfaces) of the AC3D file ``path``, in file order."""
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: file not found")
    return parse_ac3d(path.read_text(encoding="latin-1"), str(path))


def parse_ac3d(text: str, where: str = "AC3D") -> list[Ac3dPart]:
    """The parts of an AC3D file's ``text`` (see the module docstring); ``where`` names it in errors."""
    lines = _Lines(text, where)
    head = lines.next()
    if not head or not head[0].startswith("AC3D"):
        raise AssetError(f"{where}: not an AC3D file (its first line must start with 'AC3D')")
    parts: list[Ac3dPart] = []
    while lines.i < len(lines.lines):
        rest = lines.lines[lines.i:]
        if not any(r.strip() for r in rest):
            break
        tok = lines.next()
        if tok[0] == "MATERIAL":
            continue
        if tok[0] != "OBJECT":
            raise lines.error(f"expected 'MATERIAL' or 'OBJECT', got {tok[0]!r}")
        _object(lines, tok, np.eye(4), parts)
    if not parts:
        raise AssetError(f"{where}: has no surfaces")
    return parts


def ac3d_mesh(parts: list[Ac3dPart], texture: str | None = None, scale: float = 1.0) -> Mesh:
    """One :class:`Mesh` of the parts whose base texture is ``texture`` (None: the first part's),
    positions times ``scale`` (metres), ``v`` flipped to undream's convention, normals kept."""
    texture = parts[0].texture if texture is None else texture
    chosen = [p for p in parts if p.texture == texture]
    if not chosen:
        raise AssetError(f"no part of the model has the texture {texture!r} "
                         f"(textures: {sorted({str(p.texture) for p in parts})})")
    verts, nrms, uvs, faces = [], [], [], []
    base = 0
    for part in chosen:
        c = np.array(part.corners, dtype=np.float64).reshape(-1, 3)
        key = np.c_[c[:, 0], c[:, 1], c[:, 2]]
        unique, inverse = np.unique(key, axis=0, return_inverse=True)
        vi = unique[:, 0].astype(np.int64)
        tris = inverse.reshape(-1, 3)
        pos = part.vertices[vi]
        if part.normals is not None:
            n = part.normals[vi]
            n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            p = pos[tris]
            face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            flip = np.einsum("ij,ij->i", face_n, n[tris].sum(axis=1)) < 0
            tris[flip] = tris[flip][:, [0, 2, 1]]
            nrms.append(n)
        verts.append(pos)
        uvs.append(np.c_[unique[:, 1], 1.0 - unique[:, 2]])
        faces.append(tris + base)
        base += len(vi)
    normals = np.concatenate(nrms) if len(nrms) == len(chosen) else None
    return Mesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs), normals).scaled(scale)
