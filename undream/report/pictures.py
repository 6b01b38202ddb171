"""Pictures the report and the dashboard both show: a texture enlarged, its unseen texels hatched.

A texture is H×W×3 sRGB in [0, 1]; it is enlarged (nearest neighbour) to at
least :data:`TEXTURE_SIDE` pixels so that the hatching over unseen texels fits.
"""
from __future__ import annotations

import io

import numpy as np
from PIL import Image

TEXTURE_SIDE = 128  # px: a texture's short side is enlarged by a whole factor to at least this
UNSEEN_RGB = (255, 0, 255)  # the hatching over texels no frame sees
HATCH = 6  # px between hatching lines


def _enlarge(img: np.ndarray, side: int) -> tuple[np.ndarray, int]:
    """``img`` repeated by the smallest whole factor that makes its short side at least ``side`` px."""
    factor = max(1, -(-side // max(1, min(img.shape[:2]))))
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1), factor


def png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def texture_png(texture: np.ndarray, seen: np.ndarray | None) -> bytes:
    """A texture (H×W×3 sRGB, 0–1) enlarged, texels outside ``seen`` hatched in magenta."""
    img = (np.clip(np.nan_to_num(texture), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    big, factor = _enlarge(img, TEXTURE_SIDE)
    if seen is not None and seen.shape == texture.shape[:2] and not seen.all():
        unseen = np.repeat(np.repeat(~seen, factor, axis=0), factor, axis=1)
        yy, xx = np.indices(unseen.shape)
        big[unseen & ((xx + yy) % HATCH < 2)] = UNSEEN_RGB
    return png(big)
