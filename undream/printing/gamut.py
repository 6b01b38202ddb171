"""A CMYK printer's gamut as a projection of sRGB textures (``gamut`` in the run config).

The printer is a CMYK ICC profile. Its round trip ``R``: an 8-bit sRGB colour →
CMYK (8-bit) → sRGB, both ways through littleCMS (Pillow's ImageCms) with the
**relative colorimetric** intent, no black point compensation: a colour the
printer reproduces comes back (nearly) as it was, one it cannot is clipped to
the nearest colour it can (perceptual would compress every colour, printable
or not, so it would move colours that are already printable).

``R`` alone is not a projection: the profile's two tables are not exact
inverses, and the CMYK side is 8-bit, so a colour that came back from one trip
moves again on the next (Ghostscript's SWOP profile: by up to 13 levels, 2 at
the median). The projection ``P`` is defined on the 8-bit grid (all 2²⁴ colours,
precomputed once per profile and process, about 5 s and 64 MB):

- a colour ``c`` is **inside** when its round trip moves it at most
  :data:`TOLERANCE` levels (L∞, 0–255 units): ``|R(c) − c|∞ ≤ 3``;
- ``P(c) = c`` for a colour inside; else ``R(c)`` when that is inside; else
  the inside colour nearest (Euclidean, 8-bit sRGB) to ``R(c)``.

Every ``P(c)`` is inside, so ``P(P(c)) = P(c)`` exactly. A float texture
(sRGB H×W×3 in [0, 1]) is judged by the 8-bit texel it prints as (rounded):
a texel whose 8-bit colour is inside is returned as it is (bit for bit), any
other becomes ``P`` of that colour / 255. So :func:`project_gamut` is exactly
idempotent on floats too, keeps printable texels unchanged, and its result
stays a fixed point when quantised to 8 bits (the texture a run writes).

Measured for the default profile (``scripts/measure_gamut.py``): 28.7 % of the
8-bit sRGB cube is inside; an outside colour moves by 35 levels at the median
and 115 at most (pure blue (0, 0, 255) → (62, 88, 165)); ``P`` lies within
8 levels of the single round trip ``R`` for every colour (2 at the 99th percentile).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageCms
from scipy.spatial import cKDTree

from undream.color import to_uint8
from undream.errors import PrintError, SpecError
from undream.spec.printing import check_profile

TOLERANCE = 3  # 8-bit levels (L∞): a colour whose round trip moves it at most this much is printable
N_COLOURS = 1 << 24  # the 8-bit sRGB cube, colour r, g, b at index r·2¹⁶ + g·2⁸ + b


@dataclass(frozen=True, eq=False)
class Gamut:
    """A printer's gamut on the 8-bit sRGB grid: ``table[i]`` is ``P`` of colour ``i`` (2²⁴×3 uint8),
    ``inside[i]`` whether colour ``i`` is printable (2²⁴ bool, ``P`` leaves it). ``profile``: the
    CMYK profile's path; ``name``: its description; ``tolerance``: in 8-bit levels."""

    profile: Path
    name: str
    table: np.ndarray
    inside: np.ndarray
    tolerance: int = TOLERANCE

    def project(self, texture: np.ndarray) -> np.ndarray:
        """:func:`project_gamut` of ``texture`` onto this gamut."""
        return project_gamut(texture, self)

    def contains(self, texture: np.ndarray) -> np.ndarray:
        """Whether each texel of ``texture`` (sRGB H×W×3 in [0, 1]) is printable (H×W bool)."""
        return self.inside[_indices(to_uint8(_checked(texture)))]


def project_gamut(texture: np.ndarray, gamut: Gamut) -> np.ndarray:
    """``texture`` (sRGB H×W×3 float in [0, 1]) projected onto ``gamut`` (sRGB H×W×3 float32).

    Texels whose 8-bit colour is printable come back unchanged; the others become the 8-bit
    printable colour ``P`` picks for them, / 255. Exactly idempotent (see the module docstring)."""
    texture = _checked(texture).astype(np.float32, copy=False)
    idx = _indices(to_uint8(texture))
    keep = gamut.inside[idx]
    if keep.all():
        return texture.copy()
    out = texture.copy()
    out[~keep] = gamut.table[idx[~keep]].astype(np.float32) / 255.0
    return out


def _checked(texture: np.ndarray) -> np.ndarray:
    texture = np.asarray(texture)
    if texture.ndim != 3 or texture.shape[2] != 3 or not np.issubdtype(texture.dtype, np.floating):
        raise PrintError(f"texture: must be sRGB H×W×3 floats in [0, 1], got shape {texture.shape}, "
                         f"dtype {texture.dtype}")
    if texture.size and (not np.isfinite(texture).all() or texture.min() < 0 or texture.max() > 1):
        raise PrintError(f"texture: values must be finite and in [0, 1] (sRGB), got range "
                         f"[{np.nanmin(texture)}, {np.nanmax(texture)}]")
    return texture


def _indices(rgb8: np.ndarray) -> np.ndarray:
    rgb = rgb8.astype(np.int32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def _cube() -> np.ndarray:
    """Every 8-bit sRGB colour, in index order, as one 4096×4096×3 uint8 image."""
    i = np.arange(N_COLOURS, dtype=np.uint32)
    return np.stack([(i >> 16) & 255, (i >> 8) & 255, i & 255], axis=-1).astype(np.uint8).reshape(4096, 4096, 3)


def _open(path: Path) -> ImageCms.ImageCmsProfile:
    try:
        return ImageCms.getOpenProfile(str(path))
    except (ImageCms.PyCMSError, OSError) as err:
        raise SpecError(f"gamut: {path}: littleCMS cannot read the profile ({' '.join(str(err).split())})") from None


def transforms(path: Path) -> tuple[object, object]:
    """(sRGB → CMYK, CMYK → sRGB) littleCMS transforms of the CMYK profile at ``path``, 8 bits a
    channel, relative colorimetric; one-line SpecError when littleCMS cannot build them."""
    cmyk, srgb = _open(path), ImageCms.createProfile("sRGB")
    intent = ImageCms.Intent.RELATIVE_COLORIMETRIC
    try:
        return (ImageCms.buildTransform(srgb, cmyk, "RGB", "CMYK", renderingIntent=intent),
                ImageCms.buildTransform(cmyk, srgb, "CMYK", "RGB", renderingIntent=intent))
    except ImageCms.PyCMSError as err:
        raise SpecError(f"gamut: {path}: littleCMS cannot convert sRGB to and from it "
                        f"({' '.join(str(err).split())})") from None


def to_cmyk(rgb8: np.ndarray, path: Path) -> np.ndarray:
    """8-bit sRGB H×W×3 → the profile's 8-bit CMYK H×W×4 (what a print of it is sent as)."""
    forward, _ = transforms(path)
    return np.asarray(ImageCms.applyTransform(Image.fromarray(np.ascontiguousarray(rgb8), "RGB"), forward))


def round_trip(rgb8: np.ndarray, path: Path) -> np.ndarray:
    """``R``: 8-bit sRGB H×W×3 → CMYK → 8-bit sRGB through the profile at ``path``."""
    forward, back = transforms(path)
    cmyk = ImageCms.applyTransform(Image.fromarray(np.ascontiguousarray(rgb8), "RGB"), forward)
    return np.asarray(ImageCms.applyTransform(cmyk, back))


def build_gamut(path: str | Path, tolerance: int = TOLERANCE) -> Gamut:
    """The :class:`Gamut` of the CMYK profile at ``path`` (checked; about 5 s: the round trip of all
    2²⁴ colours and a nearest-neighbour search for the few whose round trip is not printable)."""
    path = check_profile(path)
    if isinstance(tolerance, bool) or not isinstance(tolerance, int) or not 0 <= tolerance <= 255:
        raise PrintError(f"tolerance: must be a whole number of 8-bit levels in [0, 255], got {tolerance!r}")
    cube = _cube().reshape(-1, 3)
    back = round_trip(cube.reshape(4096, 4096, 3), path).reshape(-1, 3)
    inside = np.abs(back.astype(np.int16) - cube.astype(np.int16)).max(axis=1) <= tolerance
    if not inside.any():
        raise SpecError(f"gamut: {path}: no sRGB colour survives the profile's round trip within "
                        f"{tolerance} levels; is it a printer profile?")
    own = np.arange(N_COLOURS, dtype=np.int32)
    pick = np.where(inside, own, _indices(back))
    lost = ~inside[pick]  # outside, and so is its round trip: the printable colour nearest to it
    if lost.any():
        targets, where = np.unique(pick[lost], return_inverse=True)
        printable = own[inside]
        _, nearest = cKDTree(cube[inside].astype(np.float32)).query(cube[targets].astype(np.float32))
        pick[lost] = printable[nearest][where]
    name = ImageCms.getProfileDescription(_open(path)).strip()
    return Gamut(path, name, cube[pick], inside, tolerance)


def load_gamut(path: str | Path, tolerance: int = TOLERANCE) -> Gamut:
    """:func:`build_gamut`, kept per process (the two last profiles; a changed file is built again)."""
    path = check_profile(Path(path).resolve())
    stat = path.stat()
    return _cached(str(path), stat.st_size, stat.st_mtime_ns, tolerance)


@functools.lru_cache(maxsize=2)
def _cached(path: str, size: int, mtime_ns: int, tolerance: int) -> Gamut:
    return build_gamut(path, tolerance)
