"""The frames an attack iteration renders: the object's window on a base, or the whole frame.

``crop: auto`` (the default) renders each iteration's frame as the object's
window (:mod:`undream.render.crop`) pasted on the frame's base, where that can
hold: the embedded Mitsuba simulator, no EOT conditions moving the camera or
light in this render, the object in the frame's mask, a window over at most
half the frame. Elsewhere, and with ``crop: off``, the frame is rendered whole
as before. The final evaluation always renders whole frames.

A base is rendered once per process, scene, frame and samples per pixel (kept
beside the loaded scenes, so the runs of a sweep that a worker serves share
them), with the scene directory's own texture and a seed of the frame alone.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from undream.engine.seeds import frame_seed
from undream.render.crop import PAD, Window, composite, crop_window
from undream.render.differentiable import render_linear
from undream.render.loading import read_texture_srgb
from undream.scenedir.verify import read_mask

BASE_ITERATION = 10**6 + 1  # the bases' seeds never coincide with an attack's or an evaluation's render
BASE_SEED = 0  # not the run's: every run of the scene composites onto the same bases


@dataclass
class CropFrames:
    """One run's windows (per frame index, read from the masks once) over its scene's shared bases."""

    ctx: Any  # the RunContext
    _windows: dict[int, Window | None] = field(default_factory=dict)

    @property
    def enabled(self) -> bool:
        cfg = self.ctx.config
        return cfg.crop == "auto" and cfg.sim == "mitsuba"

    def window(self, index: int) -> Window | None:
        """Frame ``index``'s window, or None where it is rendered whole."""
        if index not in self._windows:
            mask = read_mask(self.ctx.scene_dir, index)
            self._windows[index] = crop_window(mask, self.ctx.config.crop_margin)
        return self._windows[index]

    def render(self, index: int, texture: np.ndarray, spp: int, seed: int, conditions: Any = None) -> np.ndarray:
        """Frame ``index`` with ``texture`` (sRGB H×W×3) as the victim sees it this iteration:
        H×W×3 linear radiance, the window rendered with ``seed`` on the base, or the whole frame."""
        window = self.window(index) if self.enabled and conditions is None else None
        if window is None:
            return self.ctx.sim.render(index, texture, spp, seed, conditions=conditions)
        base = self.base(index, spp)
        h, w = base.shape[:2]
        rendered = window.grown(PAD, h, w)
        crop = render_linear(self.ctx.scenes, index, texture, spp, seed, window=rendered)
        return composite(base, window, crop, rendered)

    def base(self, index: int, spp: int) -> np.ndarray:
        """Frame ``index`` rendered whole with the scene's own texture at ``spp`` (once per process)."""
        scenes = self.ctx.scenes
        key = (index, spp)
        if key not in scenes.bases:
            texture = read_texture_srgb(scenes.mi, self.ctx.scene_dir / "textures" /
                                        f"{self.ctx.sequence.texture.name}.exr")
            scenes.bases[key] = render_linear(scenes, index, texture, spp, frame_seed(BASE_SEED, BASE_ITERATION, index))
        return scenes.bases[key]
