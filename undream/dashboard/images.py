"""The run's pictures as PNG bytes: texture versions (unseen texels marked) and evaluation frames.

Textures are H×W×3 sRGB in [0, 1] (the store's convention), drawn as the
report draws them (:func:`undream.report.pictures.texture_png`); frames are
H×W×3 uint8 sRGB; a frame goes out at its own size (the page scales it up, pixelated, and
lays a detector's boxes over it: :mod:`undream.dashboard.overlay`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from undream.errors import StoreError
from undream.report.pictures import UNSEEN_RGB, png, texture_png  # noqa: F401  (the dashboard's pictures too)

if TYPE_CHECKING:
    from undream.store import Store

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


def frame_png(frame: np.ndarray) -> bytes:
    """An evaluation frame (H×W×3 uint8) as it is: the page enlarges it, and lays a detector's boxes
    over it (:mod:`undream.dashboard.overlay`)."""
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise StoreError(f"evaluation frame: expected an H×W×3 uint8 array, got {frame.dtype} {frame.shape}")
    return png(frame)
