"""Built-in assets: procedural, UV-mapped meshes in metres.

Every built-in stands on y = 0, is centred on x = z = 0 and faces +Z where it
has a front. It is made of closed parts (so it renders from any side) whose
faces are counter-clockwise seen from outside. Normals are smooth within a
part and split (duplicated vertices) at hard edges and at UV seams.

UVs follow Mitsuba's convention (see :mod:`undream.scene.mesh`: row 0 of the
texture at v = 0, v down along rows) and form an atlas: every piece of surface
(a "chart") gets its own rectangle of [0, 1]², with a gutter of
:data:`GUTTER` between rectangles, so each texel lands on at most one place.
Charts are packed with an area share proportional to their size in metres
times a per-chart weight; the main visible surface has the largest weight.
Every chart is parameterised so that, seen from outside, the texture is not
mirrored: on vertical faces u runs to the viewer's right and v downwards, so
an image appears upright (charts without an "up", such as poles, bands and
wheels, may be turned 90° in the atlas to pack better).

Sizes (metres, see each function): sphere Ø1.0; trash_bin Ø0.62 × 1.0;
car 1.8 (x) × 1.5 (y) × 4.2 (z); umbrella Ø2.0 canopy × 2.26; traffic_cone
0.4 × 0.7 × 0.4; stop_sign 0.75 across flats, top at 2.125; pedestrian
0.62 × 1.76 × 0.24 (a box-bodied walker, legs together).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from undream.errors import AssetError
from undream.scene.mesh import Mesh, concat_meshes, load_mesh_file
from undream.spec.io import join_against
from undream.spec.model import Asset

Rect = tuple[float, float, float, float]  # (u0, v0, u1, v1)
Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (s, t) grids → positions (..., 3)

GUTTER = 0.012  # UV gap between charts and around the atlas (3 texels at 256²)
_RX180 = np.diag([1.0, -1.0, -1.0])  # turns a +Y-facing part to face −Y
_RX90 = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # +Y → +Z, −Z → +Y
_RY180 = np.diag([-1.0, 1.0, -1.0])
_Y_TO_X = np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])  # +Y axis → +X axis


@dataclass(frozen=True)
class _Chart:
    """A piece of surface with UVs in [0, 1]²; ``size`` is (along u, along v) in metres."""

    mesh: Mesh
    size: tuple[float, float]
    weight: float = 1.0  # area share ∝ weight · size[0] · size[1]
    upright: bool = True  # False: the atlas may turn it 90° (poles, bands, wheels)


# --- surface pieces (UVs in [0, 1]², not yet placed in the atlas) -----------------------------

def _grid(pos: Surface, nu: int, nv: int, uv: Callable[[np.ndarray], np.ndarray] | None = None) -> Mesh:
    """A parametric patch P(s, t), s, t ∈ [0, 1], seen from outside with s to the right and t down.

    UVs are (s, t) unless ``uv`` maps positions (K, 3) to UVs. Triangles that
    collapse (poles, apexes) are dropped; normals are smooth over the patch.
    """
    s, t = np.meshgrid(np.linspace(0.0, 1.0, nu + 1), np.linspace(0.0, 1.0, nv + 1))
    p = pos(s, t).reshape(-1, 3)
    i = np.arange(len(p)).reshape(nv + 1, nu + 1)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, 1:], i[1:, :-1]
    faces = np.concatenate([np.stack([a, d, c], -1), np.stack([a, c, b], -1)]).reshape(-1, 3)
    cross = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    faces = faces[np.linalg.norm(cross, axis=1) > 1e-12]
    uvs = np.stack([s, t], -1).reshape(-1, 2) if uv is None else uv(p)
    used, faces = np.unique(faces, return_inverse=True)
    p, faces = p[used], faces.reshape(-1, 3)
    return Mesh(p, faces, np.clip(uvs[used], 0.0, 1.0), _smooth_normals(p, faces))


def _smooth_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, shared by vertices at the same position (seams, poles)."""
    cross = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    _, key = np.unique(np.round(p * 1e7).astype(np.int64), axis=0, return_inverse=True)
    key = key.ravel()
    acc = np.zeros((key.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, key[faces[:, k]], cross)
    n = acc[key]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _revolve(radius: Callable[[np.ndarray], np.ndarray], height: Callable[[np.ndarray], np.ndarray],
             nu: int, nv: int) -> Mesh:
    """Surface of revolution about +Y; t = 0 is the top row, the u seam is at the back (−Z)."""
    def pos(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        th, r = 2.0 * np.pi * (s - 0.5), radius(t) + 0.0 * t
        return np.stack([r * np.sin(th), height(t) + 0.0 * t, r * np.cos(th)], -1)
    return _grid(pos, nu, nv)


def _disk(radius: float, segments: int, r_in: float = 0.0, phase: float = 0.0) -> Mesh:
    """A disk (or annulus) in the y = 0 plane facing +Y, UVs projected from above (+X right, −Z up)."""
    def pos(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        th, r = 2.0 * np.pi * (s - 0.5) + phase, r_in + (radius - r_in) * t
        return np.stack([r * np.sin(th), 0.0 * t, r * np.cos(th)], -1)
    return _grid(pos, segments, 1, uv=lambda p: 0.5 + p[:, [0, 2]] / (2.0 * radius))


def _quad(tl: Sequence[float], tr: Sequence[float], br: Sequence[float], bl: Sequence[float]) -> Mesh:
    """A flat quad given by its corners seen from outside (top-left, top-right, ...)."""
    q = [np.asarray(x, dtype=np.float64) for x in (tl, tr, br, bl)]
    def pos(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        s, t = s[..., None], t[..., None]
        return (1 - t) * ((1 - s) * q[0] + s * q[1]) + t * ((1 - s) * q[3] + s * q[2])
    return _grid(pos, 1, 1)


def _quad_size(q: Sequence[Sequence[float]]) -> tuple[float, float]:
    tl, tr, br, bl = (np.asarray(x, dtype=np.float64) for x in q)
    d = np.linalg.norm
    return (float(d(tr - tl) + d(br - bl)) / 2, float(d(bl - tl) + d(br - tr)) / 2)


def _strip(quads: Sequence[Sequence[Sequence[float]]], weight: float) -> _Chart:
    """Flat quads side by side in one chart (a band around an edge), quad k in u ∈ [k/n, (k+1)/n]."""
    n, parts = len(quads), []
    for k, q in enumerate(quads):
        m = _quad(*q)
        parts.append(Mesh(m.vertices, m.faces, m.uvs * [1.0 / n, 1.0] + [k / n, 0.0], m.normals))
    sizes = [_quad_size(q) for q in quads]
    size = (sum(w for w, _ in sizes), float(np.mean([h for _, h in sizes])))
    return _Chart(concat_meshes(parts), size, weight, upright=False)


# --- solids, as lists of charts -----------------------------------------------------------------

# Corners are numbered by bits (1: +x, 2: +y, 4: +z); each face lists (TL, TR, BR, BL) seen from
# outside: sides upright, the top seen from above with −Z up, the bottom from below with +Z up.
_HEXA_FACES = {"+z": (6, 7, 5, 4), "-z": (3, 2, 0, 1), "+x": (7, 3, 1, 5), "-x": (2, 6, 4, 0),
               "+y": (2, 3, 7, 6), "-y": (4, 5, 1, 0)}


def _hexa(corners: np.ndarray, weights: dict[str, float] | None = None) -> list[_Chart]:
    """A closed hexahedron (box, frustum) from its 8 corners, one flat chart per face."""
    charts = []
    for name, idx in _HEXA_FACES.items():
        q = [corners[i] for i in idx]
        charts.append(_Chart(_quad(*q), _quad_size(q), (weights or {}).get(name, 1.0)))
    return charts


def _box_corners(size: Sequence[float], center: Sequence[float]) -> np.ndarray:
    bits = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], dtype=np.float64)
    return np.asarray(center, dtype=np.float64) + (bits - 0.5) * np.asarray(size, dtype=np.float64)


def _frustum(r_bot: float, r_top: float, y_bot: float, y_top: float, segments: int, rows: int = 1,
             weights: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> list[_Chart]:
    """A closed, possibly tapered cylinder about +Y: side, top cap (+Y), bottom cap (−Y)."""
    side = _revolve(lambda t: r_top + (r_bot - r_top) * t, lambda t: y_top + (y_bot - y_top) * t,
                    segments, rows)
    top = _disk(r_top, segments).transformed(offset=(0, y_top, 0))
    bot = _disk(r_bot, segments).transformed(_RX180, (0, y_bot, 0))
    slant = math.hypot(r_bot - r_top, y_top - y_bot)
    return [_Chart(side, (math.pi * (r_bot + r_top), slant), weights[0]),
            _Chart(top, (2 * r_top, 2 * r_top), weights[1]),
            _Chart(bot, (2 * r_bot, 2 * r_bot), weights[2])]


def _move(charts: Sequence[_Chart], rotation: np.ndarray | None = None,
          offset: Sequence[float] = (0.0, 0.0, 0.0)) -> list[_Chart]:
    return [replace(c, mesh=c.mesh.transformed(rotation, offset)) for c in charts]


def _free(charts: Sequence[_Chart]) -> list[_Chart]:
    """The same charts, which the atlas may turn (their texture has no up)."""
    return [replace(c, upright=False) for c in charts]


# --- the atlas ----------------------------------------------------------------------------------

def _pack(dims: Sequence[tuple[float, float, bool]], k: float,
          gutter: float) -> list[tuple[Rect, bool]] | None:
    """Guillotine-pack (width, height, may_turn) rectangles at scale ``k`` into [0, 1]².

    Each rectangle goes, upright or (if allowed) turned, into the smallest free
    rectangle it fits; the rest of that one is split in two along the shorter
    leftover side. ``gutter`` separates rectangles. Returns (rect, turned)
    per input, or None when they overflow.
    """
    free: list[Rect] = [(gutter, gutter, 1.0, 1.0)]
    out: list[tuple[Rect, bool]] = []
    for w, h, may_turn in dims:
        w, h = w * k + gutter, h * k + gutter
        cands = [((f[2] - f[0]) * (f[3] - f[1]), f[1], f[0], turn, f) for turn in (False, True)[:1 + may_turn]
                 for f in free if f[2] - f[0] >= (h if turn else w) and f[3] - f[1] >= (w if turn else h)]
        if not cands:
            return None
        *_, turn, (x0, y0, x1, y1) = min(cands)
        free.remove((x0, y0, x1, y1))
        if turn:
            w, h = h, w
        if x1 - x0 - w < y1 - y0 - h:
            free += [(x0 + w, y0, x1, y0 + h), (x0, y0 + h, x1, y1)]
        else:
            free += [(x0 + w, y0, x1, y1), (x0, y0 + h, x0 + w, y1)]
        out.append(((x0, y0, x0 + w - gutter, y0 + h - gutter), turn))
    return out


def _place(mesh: Mesh, rect: Rect, turned: bool) -> Mesh:
    """Map a chart's [0, 1]² UVs into ``rect``, turned 90° (u ← v, v ← 1 − u) when asked."""
    uv = mesh.uvs.astype(np.float64)
    if turned:
        uv = np.stack([uv[:, 1], 1.0 - uv[:, 0]], -1)
    u0, v0, u1, v1 = rect
    return Mesh(mesh.vertices, mesh.faces, uv * [u1 - u0, v1 - v0] + [u0, v0], mesh.normals)


def _atlas(charts: Sequence[_Chart], gutter: float = GUTTER) -> Mesh:
    """Pack charts into [0, 1]² at one common scale (the largest found to fit) and merge them."""
    dims = [(c.size[0] * math.sqrt(c.weight), c.size[1] * math.sqrt(c.weight), not c.upright)
            for c in charts]
    order = sorted(range(len(charts)), key=lambda i: (-max(dims[i][:2]), -min(dims[i][:2]), i))
    sorted_dims = [dims[i] for i in order]
    k = 1.0 / max(max(d[:2]) for d in dims)
    while (packed := _pack(sorted_dims, k, gutter)) is None:  # feasibility is not monotonic in k:
        k *= 0.995  # scan down from the largest possible scale, keep the first that fits
        if k < 1e-6:
            raise AssetError("atlas: charts do not fit into the unit square")
    placed = {i: _place(charts[i].mesh, r, t) for i, (r, t) in zip(order, packed)}
    return concat_meshes([placed[i] for i in range(len(charts))])


# --- public primitives for backgrounds ----------------------------------------------------------

def box(size_xyz: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0)) -> Mesh:
    """A closed box of ``size_xyz`` metres centred at ``center``, flat normals, one chart per face."""
    return _atlas(_hexa(_box_corners(size_xyz, center)))


def cylinder(radius: float, height: float, center: Sequence[float] = (0.0, 0.0, 0.0),
             segments: int = 32) -> Mesh:
    """A closed cylinder along +Y (metres); ``center`` is the middle of its axis."""
    charts = _frustum(radius, radius, -height / 2, height / 2, segments, weights=(1.0, 0.5, 0.5))
    return _atlas(_move(charts, None, center))


# --- built-in assets ----------------------------------------------------------------------------

def sphere() -> Mesh:
    """Radius 0.5 m centred at y = 0.5; one equirectangular chart over all of [0, 1]².

    u = 0.5 faces +Z (seam at the back, −Z), v = 0 is the north pole.
    """
    return _revolve(lambda t: 0.5 * np.sin(np.pi * t), lambda t: 0.5 + 0.5 * np.cos(np.pi * t), 48, 24)


def trash_bin() -> Mesh:
    """A closed, slightly tapered bin (Ø 0.56 m at the foot, 0.60 m at 0.92 m) under a Ø 0.62 m lid.

    Total height 1.0 m; the side wall is the main chart.
    """
    n = 48
    side = _revolve(lambda t: 0.30 - 0.02 * t, lambda t: 0.92 - 0.92 * t, n, 6)
    under = _disk(0.31, n, r_in=0.30).transformed(_RX180, (0, 0.92, 0))
    band = _revolve(lambda t: 0.31 + 0.0 * t, lambda t: 1.0 - 0.08 * t, n, 1)
    lid = _disk(0.31, n).transformed(offset=(0, 1.0, 0))
    foot = _disk(0.28, n).transformed(_RX180)
    return _atlas([_Chart(side, (2 * math.pi * 0.29, 0.92), 3.0),
                   _Chart(band, (2 * math.pi * 0.31, 0.08), 1.0),
                   _Chart(lid, (0.62, 0.62), 1.5), _Chart(under, (0.62, 0.62), 0.05),
                   _Chart(foot, (0.56, 0.56), 0.2)])


def _cabin_corners() -> np.ndarray:
    c = np.zeros((8, 3))
    for i in range(8):
        top = bool(i & 2)
        c[i] = [(0.72 if top else 0.84) * (1 if i & 1 else -1), 1.5 if top else 0.90,
                ((0.25 if top else 0.95) if i & 4 else (-1.25 if top else -1.55))]
    return c


def car() -> Mesh:
    """A car 1.8 m wide (x), 1.5 m tall, 4.2 m long (z), front towards +Z.

    Lower body 1.76 × 0.64 × 4.2 m from y = 0.28, a tapered cabin up to
    y = 1.5, four wheels of radius 0.34 m and width 0.22 m along x. The lower
    body's sides carry the largest charts.
    """
    body = _hexa(_box_corners((1.76, 0.64, 4.2), (0, 0.60, 0)),
                 {"+x": 3.0, "-x": 3.0, "+z": 2.0, "-z": 2.0, "+y": 0.5, "-y": 0.02})
    cabin = _hexa(_cabin_corners(), {"-y": 0.01})
    wheels = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            w = _frustum(0.34, 0.34, -0.11, 0.11, 24, weights=(0.5, 0.3, 0.3))
            wheels += _free(_move(w, _Y_TO_X, (sx * 0.79, 0.34, sz * 1.38)))
    return _atlas(body + cabin + wheels)


def _canopy_panel(k: int, ribs: int, under: bool, radius: float, thick: float) -> Mesh:
    """Canopy between ribs k and k + 1 (flat across, curved along), top or underside, planar UVs."""
    a0, a1 = 2 * math.pi * k / ribs, 2 * math.pi * (k + 1) / ribs
    if under:
        a0, a1 = a1, a0
    d0, d1 = np.array([math.sin(a0), 0, math.cos(a0)]), np.array([math.sin(a1), 0, math.cos(a1)])

    def pos(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        p = radius * t[..., None] * ((1 - s[..., None]) * d0 + s[..., None] * d1)
        p[..., 1] = _canopy_height(t) - (thick if under else 0.0)
        return p
    flip = -1.0 if under else 1.0  # seen from below: +X right, +Z up
    return _grid(pos, 4, 8, uv=lambda p: 0.5 + p[:, [0, 2]] * [1.0, flip] / (2 * radius))


def _canopy_height(t: np.ndarray) -> np.ndarray:
    return 2.2 - 0.4 * (0.35 * t + 0.65 * t * t)


def umbrella() -> Mesh:
    """A patio umbrella: 8-rib canopy Ø 2.0 m (rib tips) from y = 2.2 (apex) to 1.8 (rim).

    The canopy is a closed 15 mm shell (top, underside, rim band) on a
    Ø 4 cm pole from 0 to 2.26 m. The canopy's top is the main chart,
    projected from above (+X right, −Z up); the underside from below.
    """
    ribs, r, thick = 8, 1.0, 0.015
    top = concat_meshes([_canopy_panel(k, ribs, False, r, thick) for k in range(ribs)])
    under = concat_meshes([_canopy_panel(k, ribs, True, r, thick) for k in range(ribs)])
    rim = [np.array([r * math.sin(a), 1.8, r * math.cos(a)])
           for a in np.linspace(0, 2 * math.pi, ribs + 1)]
    down = np.array([0.0, thick, 0.0])
    band = _strip([(rim[k], rim[k + 1], rim[k + 1] - down, rim[k] - down) for k in range(ribs)], 0.3)
    pole = _free(_frustum(0.02, 0.02, 0.0, 2.26, 16, weights=(0.5, 0.05, 0.05)))
    return _atlas([_Chart(top, (2 * r, 2 * r), 3.0), _Chart(under, (2 * r, 2 * r), 1.0), band, *pole])


def traffic_cone() -> Mesh:
    """A 0.7 m traffic cone (Ø 0.33 m at the foot, 0.05 m at the top) on a 0.4 × 0.03 × 0.4 m plate.

    The cone's side is the main chart (seam at the back, −Z).
    """
    plate = _hexa(_box_corners((0.4, 0.03, 0.4), (0, 0.015, 0)),
                  {"+y": 1.5, "-y": 0.05, "+x": 0.5, "-x": 0.5, "+z": 0.5, "-z": 0.5})
    cone = _frustum(0.165, 0.025, 0.02, 0.7, 48, rows=8, weights=(3.0, 0.3, 0.02))
    return _atlas(plate + cone)


def stop_sign() -> Mesh:
    """An octagonal sign 0.75 m across flats, 20 mm thick, centred at y = 1.75, face towards +Z.

    It hangs in front of a Ø 6 cm pole 2.1 m tall (back face at z = 0.031,
    front at z = 0.051). The front face is the main chart, upright (planar,
    top of the texture at the top of the sign); the back is upright too.
    """
    plate, pole = _sign_parts()
    return _atlas([*plate, *pole])


def stop_sign_plate() -> Mesh:
    """:func:`stop_sign` without its pole: the plate alone (x ±0.375, y 1.375–2.125, z 0.031–0.051),
    its front face the main chart. With :func:`sign_pole` as an actor, the object's mask and box
    are the sign's, as a COCO "stop sign" box is."""
    plate, _ = _sign_parts()
    return _atlas(plate)


def sign_pole() -> Mesh:
    """The stop sign's pole alone: Ø 6 cm, 2.1 m tall, centred on the y axis."""
    _, pole = _sign_parts()
    return _atlas(pole)


def _sign_parts() -> tuple[list[_Chart], list[_Chart]]:
    """The stop sign's plate charts (front, back, edge band) and its pole's."""
    across, y0, z_back, z_front = 0.75, 1.75, 0.031, 0.051
    circ = (across / 2) / math.cos(math.pi / 8)  # circumradius
    face = _disk(circ, 8, phase=math.pi / 8)
    front = face.transformed(_RX90, (0, y0, z_front))
    back = face.transformed(_RY180 @ _RX90, (0, y0, z_back))
    ang = math.pi / 8 + np.arange(9) * math.pi / 4  # octagon corners, counter-clockwise from +X
    pts = [np.array([circ * math.cos(a), y0 + circ * math.sin(a), 0.0]) for a in ang]
    zf, zb = np.array([0, 0, z_front]), np.array([0, 0, z_back])
    band = _strip([(pts[k] + zf, pts[k + 1] + zf, pts[k + 1] + zb, pts[k] + zb) for k in range(8)], 0.5)
    pole = _free(_frustum(0.03, 0.03, 0.0, 2.1, 20, weights=(0.5, 0.05, 0.05)))
    return [_Chart(front, (2 * circ, 2 * circ), 8.0), _Chart(back, (2 * circ, 2 * circ), 1.0), band], pole


def _rot_x(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1.0, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def pedestrian(phase: float = 0.0, stride_deg: float = 25.0) -> Mesh:
    """A box-bodied walker 1.76 m tall, 0.62 m across the arms, facing +Z, at ``phase`` of its gait.

    Legs (0.88 m, hips at y = 0.88) swing ±``stride_deg`` about the hips with
    ``sin(2π·phase)``, arms (0.62 m, shoulders at y = 1.45) the other way at
    0.8 of that; torso 0.42 × 0.60 × 0.24 m (its front, the shirt, is the
    main chart), head a Ø 0.2 m, 0.24 m cylinder. Phase
    0 (the built-in ``pedestrian``) has both legs straight down; one file per
    frame at phases k/n is a walk cycle (``examples/meshes/make_walker.py``).
    The parts are closed boxes that overlap at the joints.
    """
    swing = stride_deg * math.sin(2.0 * math.pi * phase)
    charts: list[_Chart] = []
    for side in (-1.0, 1.0):
        leg = _hexa(_box_corners((0.14, 0.88, 0.16), (0.0, -0.44, 0.0)), {"+z": 1.5})
        charts += _move(leg, _rot_x(side * swing), (side * 0.1, 0.88, 0.0))
        arm = _hexa(_box_corners((0.09, 0.62, 0.11), (0.0, -0.3, 0.0)), {"+z": 1.5})
        charts += _move(arm, _rot_x(-0.8 * side * swing), (side * 0.265, 1.45, 0.0))
    charts += _hexa(_box_corners((0.42, 0.60, 0.24), (0.0, 1.17, 0.0)), {"+z": 12.0, "-z": 2.0})
    charts += _free(_frustum(0.1, 0.09, 1.52, 1.76, 12, weights=(1.0, 0.2, 0.2)))
    return _atlas(charts)


BUILTINS: dict[str, Callable[[], Mesh]] = {
    "car": car, "pedestrian": pedestrian, "sign_pole": sign_pole, "sphere": sphere, "stop_sign": stop_sign,
    "stop_sign_plate": stop_sign_plate, "traffic_cone": traffic_cone, "trash_bin": trash_bin, "umbrella": umbrella,
}


def builtin_mesh(name: str) -> Mesh:
    """The built-in mesh ``name`` (see :data:`BUILTINS`), freshly generated."""
    if name not in BUILTINS:
        raise AssetError(f"unknown builtin asset {name!r} (valid: {', '.join(sorted(BUILTINS))})")
    return BUILTINS[name]()


def asset_mesh(asset: Asset, base_dir: Path | None = None, index: int | None = None) -> Mesh:
    """The asset's mesh (built-in or OBJ/PLY file) scaled by ``asset.scale``.

    Relative file paths are resolved against ``base_dir`` when given (else
    against the working directory). A per-frame mesh needs the frame ``index``.
    """
    name = asset.builtin
    if name is not None:
        mesh = builtin_mesh(name)
    else:
        if asset.per_frame and index is None:
            raise AssetError(f"{asset.mesh}: a per-frame mesh needs a frame index")
        path = Path(asset.mesh_at(index if index is not None else 0))
        mesh = load_mesh_file(join_against(path, base_dir))
    return mesh if asset.scale == 1.0 else mesh.scaled(asset.scale)
