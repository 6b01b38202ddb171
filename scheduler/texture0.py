"""A run's starting point: the scene's texture (T0) and the texels some frame sees."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from undream.render.differentiable import texture_gradient
from undream.render.loading import read_texture_srgb

if TYPE_CHECKING:
    from undream.engine.context import RunContext


def starting_texture(ctx: "RunContext") -> np.ndarray:
    """The scene directory's texture, the attack's T0: sRGB H×W×3 float32 (from the exact float EXR)."""
    return read_texture_srgb(ctx.scenes.mi, ctx.scene_dir / "textures" / f"{ctx.sequence.texture.name}.exr")


def visibility(ctx: "RunContext", texture: np.ndarray) -> np.ndarray:
    """Texels some frame sees (H×W bool): a gradient pass seeded with a white image gradient."""
    seen = np.zeros(texture.shape[:2], dtype=bool)
    for f in ctx.sequence.frames:
        res = f.camera.resolution
        g = texture_gradient(ctx.scenes, f.index, texture, np.ones((res[1], res[0], 3), np.float32),
                             ctx.config.grad_spp, ctx.config.seed, ctx.config.seed + 1)
        seen |= (g != 0).any(axis=2)
    return seen
