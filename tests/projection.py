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


def barycentric(tri: np.ndarray, xs: np.ndarray, ys: np.ndarray):
    """Barycentric coordinates (l0, l1, l2) of points (xs, ys) in a 2-D triangle (3,2); None if degenerate."""
    a, b, c = tri
    den = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
    if abs(den) < 1e-15:
        return None
    l0 = ((b[1] - c[1]) * (xs - c[0]) + (c[0] - b[0]) * (ys - c[1])) / den
    l1 = ((c[1] - a[1]) * (xs - c[0]) + (a[0] - c[0]) * (ys - c[1])) / den
    return l0, l1, 1 - l0 - l1


def rasterise(tris_px: np.ndarray, tris_z: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Z-buffer (H,W) of triangles given in pixel coordinates (T,3,2) with depths (T,3)."""
    w, h = size
    zbuf = np.full((h, w), np.inf)
    for tri, z in zip(tris_px, tris_z):
        if np.any(z < 1e-3):
            continue
        x0, y0 = np.floor(tri.min(axis=0)).astype(int)
        x1, y1 = np.ceil(tri.max(axis=0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
        if x0 > x1 or y0 > y1:
            continue
        xs, ys = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
        bary = barycentric(tri, xs, ys)
        if bary is None:
            continue
        l0, l1, l2 = bary
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        depth = 1.0 / (l0 / z[0] + l1 / z[1] + l2 / z[2])  # perspective-correct
        sub = zbuf[y0:y1 + 1, x0:x1 + 1]
        np.copyto(sub, np.minimum(sub, np.where(inside, depth, np.inf)))
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
