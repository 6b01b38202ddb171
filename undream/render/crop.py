"""Crop rendering: an iteration's frame is the object's screen region rendered anew, pasted on a base.

The texture changes only the object's own pixels and a little light it throws
on what is near it (its reflections, its colour bled onto the ground). Per
iteration the simulator therefore renders only a *window*: the box of the
object's mask (``verify/mask_NNNN.png``, one per frame, so it follows a moving
object and a camera path) grown by ``margin`` × the box's longer side on every
side and clipped to the frame. The window is rendered :data:`PAD` pixels wider
(the gaussian reconstruction filter reaches 2 px: the rim's pixels would miss
the samples of their neighbours outside) and only its inside is pasted onto
the frame's *base*: the frame rendered once, whole, with the scene's own
texture at the same samples per pixel and a seed of the frame alone, so every
process composites onto the same base and a run stays reproducible whichever
process renders which frame. Pixels outside the window keep the base's value:
exact where the texture cannot reach (tests/test_crop.py), and measured where
light from the object can (``scripts/crop_exactness.py``, docs/performance.md).

A frame gets no window (it is rendered whole) where the object is not in its
mask, or where the window would cover more than :data:`MAX_FRACTION` of the
frame (rendering it whole costs about the same). This module holds the plain
geometry and compositing; :func:`undream.render.differentiable.render_window`
renders a window.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

PAD = 2  # px rendered beyond a window and dropped: the gaussian rfilter's radius (4 × 0.5 px)
MAX_FRACTION = 0.5  # a window over more of the frame than this: the frame is rendered whole
MODES = ("auto", "off")


@dataclass(frozen=True)
class Window:
    """A pixel rectangle of a frame: columns ``x0 … x1 − 1``, rows ``y0 … y1 − 1`` (x1, y1 exclusive)."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def area(self) -> int:
        return self.width * self.height

    @property
    def slices(self) -> tuple[slice, slice]:
        """``image[window.slices]``: the window's rows and columns of an H×W(×C) image."""
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    def grown(self, px: int, height: int, width: int) -> "Window":
        """This window grown by ``px`` pixels on every side, clipped to a ``height`` × ``width`` frame."""
        return Window(max(0, self.x0 - px), max(0, self.y0 - px), min(width, self.x1 + px), min(height, self.y1 + px))

    def within(self, outer: "Window") -> tuple[slice, slice]:
        """The slices of this window inside an image of the window ``outer`` (which contains it)."""
        return (slice(self.y0 - outer.y0, self.y1 - outer.y0), slice(self.x0 - outer.x0, self.x1 - outer.x0))


def crop_window(mask: np.ndarray, margin: float, max_fraction: float = MAX_FRACTION) -> Window | None:
    """The window to render of a frame whose object covers ``mask`` (H×W bool): the mask's box grown
    by ``margin`` × its longer side (rounded up) on every side, clipped to the frame; None where the
    mask is empty or the window would cover more than ``max_fraction`` of the frame."""
    rows, cols = np.nonzero(np.asarray(mask, bool))
    if rows.size == 0:
        return None
    h, w = mask.shape[:2]
    box = Window(int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1)
    grown = box.grown(math.ceil(margin * max(box.width, box.height)), h, w)
    return None if grown.area > max_fraction * h * w else grown


def composite(base: np.ndarray, window: Window, rendered: np.ndarray, rendered_window: Window) -> np.ndarray:
    """``base`` (H×W×3) with ``window``'s pixels taken from ``rendered``, the render of
    ``rendered_window`` (a window that contains ``window``); a new array, ``base`` untouched."""
    if rendered.shape[:2] != (rendered_window.height, rendered_window.width):
        raise ValueError(f"crop render has shape {rendered.shape[:2]}, its window is "
                         f"{rendered_window.height}×{rendered_window.width}")
    out = np.array(base, dtype=np.float32, copy=True)
    out[window.slices] = rendered[window.within(rendered_window)]
    return out
