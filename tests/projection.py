"""An independent pinhole projection, from sequence.json and the PLY meshes alone.

No Mitsuba: a numpy z-buffer rasteriser of the object and its actors, with the
camera model written out from first principles (the camera looks along its
local +Z, +Y is up, +X points to the image's left; ``fov_deg`` spans the film
width; the image is the centred ``resolution`` window of the film).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from undream.scene.mesh import read_ply


def project(points_world: np.ndarray, cam: dict) -> tuple[np.ndarray, np.ndarray]:
    """World points (N,3) → image pixel coordinates (N,2) (x right, y down) and depth (N,)."""
    m = np.array(cam["to_world"], float)
    local = (np.linalg.inv(m) @ np.c_[points_world, np.ones(len(points_world))].T).T[:, :3]
    fw, fh = cam.get("film") or cam["resolution"]
    w, h = cam["resolution"]
    tan_x = np.tan(np.radians(cam["fov_deg"]) / 2)
    tan_y = tan_x * fh / fw
    z = local[:, 2]
    col = fw * (0.5 - local[:, 0] / (2 * z * tan_x)) - (fw - w) // 2
    row = fh * (0.5 - local[:, 1] / (2 * z * tan_y)) - (fh - h) // 2
    return np.c_[col, row], z


def _den(a, b, c):
    """Twice the signed area of the triangle(s) ``a, b, c`` (each (..., 2))."""
    return (b[..., 1] - c[..., 1]) * (a[..., 0] - c[..., 0]) + (c[..., 0] - b[..., 0]) * (a[..., 1] - c[..., 1])


def _weights(a, b, c, den, xs, ys):
    """Barycentric coordinates (l0, l1, l2) of points (xs, ys) in the triangle(s) ``a, b, c``."""
    l0 = ((b[..., 1] - c[..., 1]) * (xs - c[..., 0]) + (c[..., 0] - b[..., 0]) * (ys - c[..., 1])) / den
    l1 = ((c[..., 1] - a[..., 1]) * (xs - c[..., 0]) + (a[..., 0] - c[..., 0]) * (ys - c[..., 1])) / den
    return l0, l1, 1 - l0 - l1


def barycentric(tri: np.ndarray, xs: np.ndarray, ys: np.ndarray):
    """Barycentric coordinates (l0, l1, l2) of points (xs, ys) in a 2-D triangle (3,2); None if degenerate."""
    a, b, c = tri
    den = _den(a, b, c)
    if abs(den) < 1e-15:
        return None
    return _weights(a, b, c, den, xs, ys)


def rasterise(tris_px: np.ndarray, tris_z: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Z-buffer (H,W) of triangles given in pixel coordinates (T,3,2) with depths (T,3): every pixel
    centre of a triangle's bounding box tested at once (one array of (triangle, pixel) pairs)."""
    w, h = size
    zbuf = np.full((h, w), np.inf)
    tris_px, tris_z = np.asarray(tris_px, float), np.asarray(tris_z, float)
    lo, hi = np.floor(tris_px.min(axis=1)).astype(int), np.ceil(tris_px.max(axis=1)).astype(int)
    x0, y0 = np.maximum(lo[:, 0], 0), np.maximum(lo[:, 1], 0)
    x1, y1 = np.minimum(hi[:, 0], w - 1), np.minimum(hi[:, 1], h - 1)
    a, b, c = tris_px[:, 0], tris_px[:, 1], tris_px[:, 2]
    den = _den(a, b, c)
    keep = (tris_z >= 1e-3).all(axis=1) & (x0 <= x1) & (y0 <= y1) & (np.abs(den) >= 1e-15)
    t = np.flatnonzero(keep)
    if t.size == 0:
        return zbuf
    bw, bh = x1[t] - x0[t] + 1, y1[t] - y0[t] + 1
    counts = bw * bh
    pair_t = np.repeat(t, counts)  # each triangle once per pixel of its box
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)  # index inside the box
    bw_p = np.repeat(bw, counts)
    xs, ys = x0[pair_t] + k % bw_p, y0[pair_t] + k // bw_p
    l0, l1, l2 = _weights(a[pair_t], b[pair_t], c[pair_t], den[pair_t], xs + 0.5, ys + 0.5)
    inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    z = tris_z[pair_t[inside]]
    depth = 1.0 / (l0[inside] / z[:, 0] + l1[inside] / z[:, 1] + l2[inside] / z[:, 2])  # perspective-correct
    np.minimum.at(zbuf, (ys[inside], xs[inside]), depth)
    return zbuf


def _world_tris(mesh, to_world) -> np.ndarray:
    m = np.array(to_world, float)
    v = (m @ np.c_[mesh.vertices, np.ones(len(mesh.vertices))].T).T[:, :3]
    return v[mesh.faces]


def mesh_file(scene_dir: Path, name: str, index: int) -> Path:
    """``meshes/NAME.ply``, or frame ``index``'s ``meshes/NAME_NNNN.ply`` of a per-frame mesh."""
    static = Path(scene_dir) / "meshes" / f"{name}.ply"
    return static if static.is_file() else Path(scene_dir) / "meshes" / f"{name}_{index:04d}.ply"


def visible_mask(scene_dir: Path, frame: dict, seq: dict, actors: bool = True) -> np.ndarray:
    """Pixels where the object is the nearest surface among the object and (``actors``) the actors."""
    cam = frame["camera"]
    size = tuple(cam["resolution"])
    obj = _world_tris(read_ply(mesh_file(scene_dir, "object", frame["index"])), frame["object_to_world"])
    zbuf_obj = _zbuf(obj, cam, size)
    zbuf_occ = np.full_like(zbuf_obj, np.inf)
    for a in frame["actors"] if actors else ():
        tris = _world_tris(read_ply(mesh_file(scene_dir, a["name"], frame["index"])), a["to_world"])
        zbuf_occ = np.minimum(zbuf_occ, _zbuf(tris, cam, size))
    return np.isfinite(zbuf_obj) & (zbuf_obj <= zbuf_occ)


def _zbuf(tris: np.ndarray, cam: dict, size) -> np.ndarray:
    px, z = project(tris.reshape(-1, 3), cam)
    return rasterise(px.reshape(-1, 3, 2), z.reshape(-1, 3), size)


def centroid(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5])


def load(scene_dir: Path) -> dict:
    return json.loads((scene_dir / "sequence.json").read_text())
