"""Rendering a scene directory's frames with a given texture, and the texture gradient.

The texture handed in and out is sRGB in [0, 1] (H×W×3, what a user prints);
the scenes hold linear reflectance, so the conversion is applied here, inside
the differentiable path. Loaded scenes are cached per process: each frame's
kernels compile once, and later calls only update the texture via
``mi.traverse``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from undream.errors import RenderError
from undream.color import linear_to_srgb, srgb_to_linear
from undream.render.loading import load_scene, texture_param_key
from undream.scene.layout import frame_name


@dataclass
class _Loaded:
    scene: Any
    params: Any
    key: str


class FrameScenes:
    """Per-process cache of a scene directory's ``sim`` and ``grad`` scenes."""

    def __init__(self, scene_dir: str | Path, mi: Any | None = None):
        from undream.variant import mitsuba

        self.dir = Path(scene_dir)
        self.mi = mi or mitsuba()
        self._cache: dict[tuple[str, int], _Loaded] = {}

    def get(self, kind: str, index: int) -> _Loaded:
        if (kind, index) not in self._cache:
            xml = self.dir / "frames" / f"{frame_name(kind, index)}.xml"
            if not xml.is_file():
                raise RenderError(f"{xml}: no such frame file (is {self.dir} a scene directory?)")
            scene = load_scene(self.mi, xml, spp=1)
            params = self.mi.traverse(scene)
            self._cache[(kind, index)] = _Loaded(scene, params, texture_param_key(params))
        return self._cache[(kind, index)]

    def _set_texture(self, loaded: _Loaded, texture_srgb: np.ndarray) -> Any:
        lin = srgb_to_linear(_check_texture(texture_srgb, loaded.params[loaded.key].shape))
        loaded.params[loaded.key] = self.mi.TensorXf(lin)
        loaded.params.update()
        return loaded.params[loaded.key]


def _check_texture(tex: np.ndarray, shape: Any) -> np.ndarray:
    tex = np.asarray(tex, dtype=np.float32)
    if tex.shape != tuple(shape):
        raise RenderError(f"texture has shape {tex.shape}, the scene's is {tuple(shape)} (H, W, 3)")
    if not np.isfinite(tex).all():
        raise RenderError("texture contains NaN or Inf")
    return tex


def render_linear(scenes: FrameScenes, index: int, texture_srgb: np.ndarray, spp: int, seed: int) -> np.ndarray:
    """The simulation render of frame ``index``: H×W×3 LINEAR radiance (unclipped)."""
    loaded = scenes.get("sim", index)
    scenes._set_texture(loaded, texture_srgb)
    return np.array(scenes.mi.render(loaded.scene, spp=spp, seed=seed), dtype=np.float32)


def render_srgb(scenes: FrameScenes, index: int, texture_srgb: np.ndarray, spp: int, seed: int) -> np.ndarray:
    """The simulation render as the camera delivers it: H×W×3 sRGB in [0, 1]."""
    return linear_to_srgb(render_linear(scenes, index, texture_srgb, spp, seed))


def srgb_encode_grad(linear: np.ndarray, grad_srgb: np.ndarray) -> np.ndarray:
    """d(loss)/d(linear image) from d(loss)/d(sRGB image), at the linear image ``linear``.

    The encoding clips to [0, 1]: saturated pixels pass no gradient.
    """
    x = np.asarray(linear, np.float32)
    inside = (x > 0.0) & (x < 1.0)
    xc = np.clip(x, 1e-8, 1.0)
    deriv = np.where(xc <= 0.0031308, 12.92, 1.055 / 2.4 * np.power(xc, 1 / 2.4 - 1.0))
    return (np.asarray(grad_srgb, np.float32) * deriv * inside).astype(np.float32)


def srgb_decode_grad(texture_srgb: np.ndarray, grad_linear: np.ndarray) -> np.ndarray:
    """d(loss)/d(sRGB texture) from d(loss)/d(linear texture), at the sRGB texture."""
    t = np.asarray(texture_srgb, np.float32)
    deriv = np.where(t <= 0.04045, 1 / 12.92, 2.4 / 1.055 * np.power((np.maximum(t, 0.04045) + 0.055) / 1.055, 1.4))
    return (np.asarray(grad_linear, np.float32) * deriv).astype(np.float32)


def texture_gradient(scenes: FrameScenes, index: int, texture_srgb: np.ndarray, grad_linear_image: np.ndarray,
                     spp: int, seed: int, seed_grad: int) -> np.ndarray:
    """Mitsuba's backward pass of frame ``index``'s gradient scene, seeded with an image gradient.

    ``grad_linear_image`` is d(loss)/d(linear image) (H×W×3); returns
    d(loss)/d(sRGB texture) (H×W×3). ``seed_grad`` must differ from ``seed``.
    """
    import drjit as dr

    if seed == seed_grad:
        raise RenderError(f"seed_grad must differ from seed (both {seed}): prb needs decorrelated samples")
    loaded = scenes.get("grad", index)
    tex = scenes._set_texture(loaded, texture_srgb)
    dr.enable_grad(tex)
    loaded.params.update()
    img = scenes.mi.render(loaded.scene, loaded.params, spp=spp, seed=seed, seed_grad=seed_grad)
    g = scenes.mi.TensorXf(np.ascontiguousarray(grad_linear_image, dtype=np.float32))
    if tuple(g.shape) != tuple(img.shape):
        raise RenderError(f"image gradient has shape {tuple(g.shape)}, the render's is {tuple(img.shape)}")
    dr.backward(img * g)
    grad_lin = np.array(dr.grad(loaded.params[loaded.key]), dtype=np.float32)
    dr.disable_grad(loaded.params[loaded.key])
    return srgb_decode_grad(texture_srgb, grad_lin)
