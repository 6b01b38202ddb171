"""Verification renders of a scene directory: white-texture frames and visibility masks.

A mask is the object's visible pixels in one frame (H×W bool, coverage > 0.5
behind every occluder), saved as ``verify/mask_NNNN.png`` (0 or 255) and read
back by :func:`read_mask`; :func:`mask_box` is the object's box in it.
"""
from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any, Iterator

import numpy as np
from PIL import Image, ImageDraw

from undream import interrupts
from undream.color import linear_to_srgb, to_uint8
from undream.errors import SpecError
from undream.render.differentiable import render_frozen
from undream.render.loading import load_scene, texture_param_key
from undream.render.scene_cache import SceneCache
from undream.scene.layout import mask_png
from undream.scene.mitsuba_scene import ScenePaths, scene_dict
from undream.scene.xml import to_mitsuba
from undream.spec import Frame, Sequence
from undream.spec.io import naming


def render_white(mi: ModuleType, xml: Path, spp: int, seed: int = 0) -> np.ndarray:
    """Render a simulation scene with a plain white texture: H×W×3 linear RGB."""
    scene = load_scene(mi, xml, spp)
    params = mi.traverse(scene)
    key = texture_param_key(params)
    params[key] = mi.TensorXf(np.ones(params[key].shape, dtype=np.float32))
    params.update()
    return np.array(mi.render(scene, seed=seed), dtype=np.float32)


def render_frames(mi: ModuleType, scene_dir: Path, indices: list[int], spp: int,
                  frozen: bool = True) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Each frame's white render (H×W×3 linear, as :func:`render_white`) and mask (H×W bool, as
    :func:`render_mask`), from the scene directory's ``frames/sim_NNNN.xml`` and
    ``frames/mask_NNNN.xml`` (the init writes the latter for this and removes them after).

    One loaded scene per group of equal frames (:class:`~undream.render.scene_cache.SceneCache`),
    each render a Dr.Jit frozen function replayed with the frame's values (``frozen``), instead of
    loading, tracing and compiling two scenes per frame: what makes the init of a multi-condition
    run's hundreds of frames take minutes less.
    """
    scenes = SceneCache(scene_dir, mi, frozen=frozen)
    white: dict[tuple[int, ...], Any] = {}
    try:
        for index in indices:
            loaded = scenes.loaded("sim", index)
            shape = tuple(loaded.params[loaded.texture_key].shape)
            if shape not in white:
                white[shape] = mi.TensorXf(np.ones(shape, dtype=np.float32))
            img = render_frozen(scenes, "sim", scenes.frame("sim", index, texture=white[shape]), spp, 0)
            cover = render_frozen(scenes, "mask", scenes.frame("mask", index), spp, 0)
            # a signal whose exception was dropped on its way out (raised in a callback Dr.Jit or
            # Python swallowed) ends the init here: tests/test_interrupts.py saw `init` finish with 0
            interrupts.check()
            yield index, img, cover.mean(axis=2) > 0.5
    finally:
        scenes.close()


def render_mask(mi: ModuleType, seq: Sequence, frame: Frame, scene_dir: Path, spp: int) -> np.ndarray:
    """Visible pixels of the object (H×W bool): coverage > 0.5 behind all occluders."""
    d = scene_dict(seq, frame, ScenePaths(str(scene_dir.resolve())), "mask")
    scene = mi.load_dict(to_mitsuba(d, mi, {"spp": spp}))
    img = np.array(mi.render(scene, seed=0), dtype=np.float32)
    return img.mean(axis=2) > 0.5


def save_rgb(linear: np.ndarray, path: Path) -> None:
    with naming(path):
        Image.fromarray(to_uint8(linear_to_srgb(linear))).save(path)


def save_mask(mask: np.ndarray, path: Path) -> None:
    with naming(path):
        Image.fromarray((mask.astype(np.uint8) * 255)).save(path)


def read_mask(scene_dir: str | Path, index: int) -> np.ndarray:
    """Frame ``index``'s mask (H×W bool) from ``scene_dir/verify/mask_NNNN.png``."""
    return np.asarray(Image.open(mask_png(scene_dir, index))) > 127


def check_visible(scene_dir: str | Path, indices: list[int]) -> None:
    """SpecError unless the object shows in at least one frame's mask (``verify/mask_NNNN.png``):
    a run on a scene that never shows it would judge nothing and report 0 → 0."""
    if not any(read_mask(scene_dir, i).any() for i in indices):
        raise SpecError(_UNSEEN.format(n=len(indices)))


_UNSEEN = ("the object is visible in 0 of {n} frames (its masks verify/mask_*.png are empty: the camera is "
           "inside it, looks away from it, or something hides it); move the camera or the object; nothing written")


def check_seen(scene_dir: str | Path, seq: Sequence) -> None:
    """:func:`check_visible` over the whole sequence and, for a multi-condition sequence, over each
    condition's frames: a condition in which the object is never seen would be attacked and judged on
    nothing (it reported 0.0 → 0.0); SpecError naming the condition."""
    seen = {f.index: bool(read_mask(scene_dir, f.index).any()) for f in seq.frames}
    if not any(seen.values()):
        raise SpecError(_UNSEEN.format(n=len(seen)))
    if not seq.conditions:
        return
    for part, span in seq.condition_ranges():
        if not any(seen[seq.frames[i].index] for i in span):
            raise SpecError(f"condition {part.name!r}: the object is visible in 0 of {len(span)} frames (their "
                            "masks are empty: its camera looks away from the object, is inside it, or something "
                            "hides it); change or drop the condition; nothing written")


def mask_box(mask: np.ndarray) -> tuple[float, float, float, float] | None:
    """``(x0, y0, x1, y1)`` pixel box (edges, x1/y1 exclusive) of a boolean H×W mask, or None."""
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return None
    return float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1)


def contact_sheet(tiles: list[tuple[str, np.ndarray, np.ndarray]], path: Path, columns: int = 4) -> None:
    """A grid of white renders (sRGB uint8) with the mask's outline in red and a label each."""
    if not tiles:
        return
    h, w = tiles[0][1].shape[:2]
    zoom = max(1, int(np.ceil(160 / max(h, w))))
    tw, th = w * zoom, h * zoom + 14
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    sheet = Image.new("RGB", (cols * tw, rows * th), (24, 24, 24))
    for i, (label, rgb, mask) in enumerate(tiles):
        img = rgb.copy()
        edge = mask & ~_eroded(mask)
        img[edge] = (255, 40, 40)
        tile = Image.fromarray(img).resize((tw, th - 14), Image.NEAREST)
        x, y = (i % cols) * tw, (i // cols) * th
        sheet.paste(tile, (x, y + 14))
        ImageDraw.Draw(sheet).text((x + 3, y + 1), label, fill=(230, 230, 230))
    with naming(path):
        sheet.save(path)


def _eroded(mask: np.ndarray) -> np.ndarray:
    m = np.pad(mask, 1, constant_values=False)
    return m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
