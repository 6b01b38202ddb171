"""The frames an attack iteration renders: the object's window on a base, or the whole frame.

``crop: auto`` (the default) renders each iteration's frame as the object's
window (:mod:`undream.render.crop`) pasted on the frame's base, where that can
hold: the embedded Mitsuba simulator, no EOT conditions moving the camera or
light in this render, a frame of at least ``crop_min_pixels`` pixels (128², by
default: on 64-px frames a window's base and first recording cost what its
uses saved), the object in the frame's mask, a window over at most half the
frame. Elsewhere, and with ``crop: off``, the frame is rendered whole as before.
The final evaluation always renders whole frames.

``media: auto`` (the default) renders the window of a frame whose simulation
scene holds a medium (fog, rain's and snow's haze) without it, through the
frame's gradient scene, mapped into the medium's look (:mod:`undream.render.media`;
the image gradient scaled by the same ``α``, :meth:`CropFrames.scale_gradient`);
``media: exact`` path traces the medium in every window.

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
from undream.render.media import MediumModel, fit_medium, render_clear, scale_gradient, sigma_t_of
from undream.scenedir.verify import read_mask

BASE_ITERATION = 10**6 + 1  # the bases' seeds never coincide with an attack's or an evaluation's render
BASE_SEED = 0  # not the run's: every run of the scene composites onto the same bases


@dataclass
class CropFrames:
    """One run's windows (per frame index, read from the masks once) over its scene's shared bases."""

    ctx: Any  # the RunContext
    _windows: dict[int, Window | None] = field(default_factory=dict)
    _media: dict[tuple[int, int], MediumModel | None] = field(default_factory=dict)  # (index, spp) → model
    _start: np.ndarray | None = None  # the scene's own texture, read once (every base and medium fit uses it)

    @property
    def enabled(self) -> bool:
        cfg = self.ctx.config
        return cfg.crop == "auto" and cfg.sim == "mitsuba"

    def window(self, index: int) -> Window | None:
        """Frame ``index``'s window, or None where it is rendered whole."""
        if index not in self._windows:
            mask = read_mask(self.ctx.scene_dir, index)
            small = mask.size < self.ctx.config.crop_min_pixels
            self._windows[index] = None if small else crop_window(mask, self.ctx.config.crop_margin)
        return self._windows[index]

    def render(self, index: int, texture: np.ndarray, spp: int, seed: int, conditions: Any = None) -> np.ndarray:
        """Frame ``index`` with ``texture`` (sRGB H×W×3) as the victim sees it this iteration:
        H×W×3 linear radiance, the window rendered with ``seed`` on the base, or the whole frame; in a
        medium with ``media: auto``, the window mapped from the gradient scene's at the frame's own
        fixed seed (:meth:`medium`; ``seed`` unused)."""
        window = self.window(index) if self.enabled and conditions is None else None
        if window is None:
            return self.ctx.sim.render(index, texture, spp, seed, conditions=conditions)
        base = self.base(index, spp)
        h, w = base.shape[:2]
        rendered = window.grown(PAD, h, w)
        model = self.medium(index, spp)
        if model is not None:
            change = model.window(render_clear(self.ctx.scenes, index, model, texture, spp))
            return composite(base, window, base[rendered.slices] + change, rendered)
        crop = render_linear(self.ctx.scenes, index, texture, spp, seed, window=rendered)
        return composite(base, window, crop, rendered)

    def medium(self, index: int, spp: int) -> MediumModel | None:
        """Frame ``index``'s medium model at ``spp`` (fitted once per process), or None where its
        window is path traced as it is: ``media: exact``, no medium, no window."""
        if self.ctx.config.media != "auto" or not self.enabled:
            return None
        key = (index, spp)
        if key not in self._media:
            window = self.window(index)
            sigma_t = sigma_t_of(self._frame(index).environment)
            if window is None or sigma_t is None:
                self._media[key] = None
            else:
                base = self.base(index, spp)
                rendered = window.grown(PAD, *base.shape[:2])
                self._media[key] = fit_medium(self.ctx.scenes, index, rendered, self._texture(), sigma_t, spp,
                                              frame_seed(BASE_SEED, BASE_ITERATION, index))
        return self._media[key]

    def scale_gradient(self, index: int, spp: int, grad_linear_image: np.ndarray, conditions: Any = None) -> np.ndarray:
        """d(loss)/d(linear frame) carried to the gradient scene's image: unchanged, or where the
        frame's window was mapped into its medium, ``α`` times it inside the window and 0 outside."""
        model = self.medium(index, spp) if conditions is None else None
        window = self.window(index) if model is not None else None
        if model is None or window is None:
            return grad_linear_image
        return scale_gradient(model, window, grad_linear_image)

    def _frame(self, index: int) -> Any:
        return next(f for f in self.ctx.sequence.frames if f.index == index)

    def _texture(self) -> np.ndarray:
        if self._start is None:
            self._start = read_texture_srgb(self.ctx.scenes.mi, self.ctx.scene_dir / "textures" /
                                            f"{self.ctx.sequence.texture.name}.exr")
        return self._start

    def base(self, index: int, spp: int) -> np.ndarray:
        """Frame ``index`` rendered whole with the scene's own texture at ``spp`` (once per process)."""
        scenes = self.ctx.scenes
        key = (index, spp)
        if key not in scenes.bases:
            scenes.bases[key] = render_linear(scenes, index, self._texture(), spp,
                                              frame_seed(BASE_SEED, BASE_ITERATION, index))
        return scenes.bases[key]
