"""The embedded simulator: Mitsuba path-traces each frame's simulation scene (``frames/sim_NNNN.xml``)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from undream.render.differentiable import render_linear
from undream.render.scene_cache import SceneCache
from undream.sim import register_backend


@register_backend("mitsuba")
class MitsubaSimulator:
    """Renders through a :class:`SceneCache` (shared with the gradient renders when one is given)."""

    name = "mitsuba"

    def __init__(self, scene_dir: Path, scenes: SceneCache | None = None):
        self.scenes = scenes or SceneCache(scene_dir)

    def render(self, index: int, texture_srgb: np.ndarray, spp: int, seed: int,
               conditions: Any = None) -> np.ndarray:
        return render_linear(self.scenes, index, texture_srgb, spp, seed, conditions=conditions)

    def versions(self) -> dict[str, str]:
        import drjit

        mi = self.scenes.mi
        return {"mitsuba": mi.__version__, "drjit": drjit.__version__, "variant": str(mi.variant())}
