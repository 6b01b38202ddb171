"""The run's pictures as PNG bytes: texture versions (unseen texels marked) and evaluation frames.

Textures are H×W×3 sRGB in [0, 1] (the store's convention); frames are
H×W×3 uint8 sRGB. A texture is enlarged (nearest neighbour) to at least
:data:`TEXTURE_SIDE` pixels so that the hatching over unseen texels fits;
a frame goes out at its own size (the page scales it up, pixelated, and
lays a detector's boxes over it: :mod:`undream.dashboard.overlay`).
"""
from __future__ import annotations

import io
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from undream.errors import StoreError

if TYPE_CHECKING:
    from undream.store import Store

TEXTURE_SIDE = 128  # px: a texture's short side is enlarged by a whole factor to at least this
UNSEEN_RGB = (255, 0, 255)  # the hatching over texels no frame sees
HATCH = 6  # px between hatching lines


def _enlarge(img: np.ndarray, side: int) -> tuple[np.ndarray, int]:
    """``img`` repeated by the smallest whole factor that makes its short side at least ``side`` px."""
    factor = max(1, -(-side // max(1, min(img.shape[:2]))))
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1), factor


def _png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def seen_mask(store: "Store", run_id: str) -> np.ndarray | None:
    """H×W bool: texels some frame sees, or None when unknown.

    From the starting attack state's ``visible`` array (runs with a random
    start), else the mask kept when iteration 0 was reduced (its gradients
    are deleted then), else the texels where some frame's gradient of
    iteration 0 is not zero (while iteration 0 runs).
    """
    state0 = store.attack_state(run_id, 0) or {}
    visible = state0.get("visible")
    if isinstance(visible, np.ndarray) and visible.ndim == 2 and visible.any():
        return visible.astype(bool)
    kept = store.seen_mask(run_id)
    if kept is not None:
        return kept
    seen = None
    for job in store.jobs(run_id, 0, "attack"):
        if job.status != "succeeded" or job.grad_ref is None:
            continue
        try:
            grad = store.blobs.get_array(job.grad_ref)
        except StoreError:  # deleted meanwhile: iteration 0 was reduced, and its mask kept
            return store.seen_mask(run_id)
        if grad.ndim != 3:
            continue
        hit = np.any(grad != 0, axis=2)
        seen = hit if seen is None else (seen | hit if seen.shape == hit.shape else seen)
    return seen


def texture_png(texture: np.ndarray, seen: np.ndarray | None) -> bytes:
    """A texture (H×W×3 sRGB, 0–1) enlarged, texels outside ``seen`` hatched in magenta."""
    img = (np.clip(np.nan_to_num(texture), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    big, factor = _enlarge(img, TEXTURE_SIDE)
    if seen is not None and seen.shape == texture.shape[:2] and not seen.all():
        unseen = np.repeat(np.repeat(~seen, factor, axis=0), factor, axis=1)
        yy, xx = np.indices(unseen.shape)
        big[unseen & ((xx + yy) % HATCH < 2)] = UNSEEN_RGB
    return _png(big)


def frame_png(frame: np.ndarray) -> bytes:
    """An evaluation frame (H×W×3 uint8) as it is: the page enlarges it, and lays a detector's boxes
    over it (:mod:`undream.dashboard.overlay`)."""
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise StoreError(f"evaluation frame: expected an H×W×3 uint8 array, got {frame.dtype} {frame.shape}")
    return _png(frame)
