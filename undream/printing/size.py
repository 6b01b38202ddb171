"""A texture's real size on its mesh: metres per texel from the triangles' 3D and UV areas.

Each triangle covers an area ``A`` (m²) on the object and ``a`` (UV units², after the
texture's ``uv_scale``: a texture repeated twice along u has its u doubled) in the
texture. Over the UV charts, the texture's unit square covers ``ΣA / Σa`` m² of the
object, so a texel of a W×H texture covers ``ΣA / (Σa·W·H)`` m², and a square
texel's side is the square root of that. An area-weighted mean: charts stretched
more than others print at the mean scale. Triangles with no UV area (seams,
degenerate triangles) are left out of both sums.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from undream.errors import PrintError


@dataclass(frozen=True)
class TexelSize:
    """``metres``: a texel's side on the object (m); ``width_m``, ``height_m``: the whole texture's
    (W·side, H·side), what one repeat of it covers; ``area_m2`` and ``uv_area``: the sums it came from."""

    metres: float
    width_m: float
    height_m: float
    area_m2: float
    uv_area: float


def texel_size(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture_wh: tuple[int, int],
               uv_scale: tuple[float, float] = (1.0, 1.0), scale: float = 1.0) -> TexelSize:
    """The :class:`TexelSize` of a W×H texture (``texture_wh``) on a mesh: ``vertices`` N×3 (metres,
    times ``scale``: the object's own scale in the scene), ``faces`` F×3 vertex indices, ``uvs``
    N×2 per vertex (u, v), repeated ``uv_scale`` times. PrintError when no triangle has UV area."""
    v = np.asarray(vertices, np.float64) * float(scale)
    f = np.asarray(faces, np.int64)
    uv = np.asarray(uvs, np.float64) * np.asarray(uv_scale, np.float64)
    w, h = texture_wh
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or uv.shape != (len(v), 2):
        raise PrintError(f"mesh: needs N×3 vertices, F×3 faces and N×2 UVs, got {v.shape}, {f.shape}, {uv.shape}")
    if w < 1 or h < 1:
        raise PrintError(f"texture: must be at least 1×1 texels, got {w}×{h}")
    area3 = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    e1, e2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    area_uv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    used = area_uv > 1e-12
    total3, total_uv = float(area3[used].sum()), float(area_uv[used].sum())
    if total_uv <= 0 or total3 <= 0:
        raise PrintError("mesh: no triangle has both a surface and a UV area; the texture has no real size on it")
    side = float(np.sqrt(total3 / (total_uv * w * h)))
    return TexelSize(side, side * w, side * h, total3, total_uv)
