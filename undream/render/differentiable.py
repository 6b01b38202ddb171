"""Rendering a frame with a given texture, and the texture gradient through the frame's gradient scene.

The texture handed in and out is sRGB in [0, 1] (H×W×3, what a user prints);
the scenes hold linear reflectance, so the conversion is applied here, inside
the differentiable path. Scenes come from a per-process
:class:`~undream.render.scene_cache.SceneCache`. With ``scenes.frozen`` the
forward render runs as a Dr.Jit frozen function: traced once per scene
group, then replayed with the frame's parameters, texture and seed as inputs.
The backward pass calls the integrator's ``render_backward`` directly (no
primal image of the gradient scene is rendered: it was never used).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from undream.color import srgb_to_linear
from undream.errors import RenderError
from undream.render.scene_cache import ActiveFrame, SceneCache, update_params

if TYPE_CHECKING:
    from undream.render.crop import Window


def _check_texture(tex: np.ndarray, shape: Any) -> np.ndarray:
    tex = np.asarray(tex, dtype=np.float32)
    if tex.shape != tuple(shape):
        raise RenderError(f"texture has shape {tex.shape}, the scene's is {tuple(shape)} (H, W, 3)")
    if not np.isfinite(tex).all():
        raise RenderError("texture contains NaN or Inf")
    return tex


def _linear_texture(scenes: SceneCache, active: ActiveFrame, texture_srgb: np.ndarray) -> Any:
    """The sRGB texture as Mitsuba's linear-reflectance tensor of ``active``'s shape."""
    return scenes.mi.TensorXf(srgb_to_linear(_check_texture(texture_srgb, active.params[active.texture_key].shape)))


def _render_texture(scenes: SceneCache, active: ActiveFrame, texture_srgb: np.ndarray) -> Any:
    """:func:`_linear_texture`, converted once for the frames that render the same texture in a row
    (``scenes.render_texture`` keeps the last sRGB texture's tensor)."""
    tex = np.asarray(texture_srgb, dtype=np.float32)
    if tex.shape != tuple(active.params[active.texture_key].shape):
        return _linear_texture(scenes, active, tex)  # raises, naming both shapes
    return scenes.render_texture.get(tex, lambda t: _linear_texture(scenes, active, t))


def render_linear(scenes: SceneCache, index: int, texture_srgb: np.ndarray, spp: int, seed: int,
                  kind: str = "sim", conditions: Any = None, window: "Window | None" = None) -> np.ndarray:
    """The render of frame ``index``'s ``kind`` scene (simulation by default): H×W×3 LINEAR radiance
    (unclipped); ``conditions``: the camera and light moved for this render (:mod:`undream.render.jitter`);
    ``window`` (:class:`undream.render.crop.Window`): only that region, ``height × width × 3``."""
    # the texture written with the frame's own values: one scene update (the conditions, if any, after)
    texture = _render_texture(scenes, scenes.loaded(kind, index), texture_srgb)
    active = scenes.frame(kind, index, conditions, texture=texture)
    if window is None:
        return render_frozen(scenes, kind, active, spp, seed)
    return render_window(scenes, kind, active, spp, seed, window)


def render_window(scenes: SceneCache, kind: str, active: ActiveFrame, spp: int, seed: int,
                  window: "Window") -> np.ndarray:
    """``mi.render`` of the region ``window`` of ``active``'s film (its crop window; the camera
    is the whole frame's): ``window.height × window.width × 3`` linear radiance. The film is whole
    again afterwards. Frozen (when ``scenes.frozen``) per window: a film's crop is a host-side value
    that a recording holds as a constant, so each window has its own recording."""
    mi = scenes.mi
    params = active.params
    size = params["sensor.film.size"]
    if not (0 <= window.x0 < window.x1 <= size[0] and 0 <= window.y0 < window.y1 <= size[1]):
        raise RenderError(f"crop window {window} is not inside the {size[0]}×{size[1]} film")
    params["sensor.film.crop_offset"] = mi.ScalarPoint2u(window.x0, window.y0)
    params["sensor.film.crop_size"] = mi.ScalarVector2u(window.width, window.height)
    update_params(params)
    try:
        if scenes.frozen:
            name = f"render/{kind}/{window.x0},{window.y0},{window.width}x{window.height}"
            img = scenes.frozen_call(name, _render, active.scene, mi.UInt32(seed), spp, scene=active.scene)
        else:
            img = mi.render(active.scene, spp=spp, seed=seed)
        return np.array(img, dtype=np.float32)
    finally:
        params["sensor.film.crop_offset"] = mi.ScalarPoint2u(0, 0)
        params["sensor.film.crop_size"] = mi.ScalarVector2u(int(size[0]), int(size[1]))
        update_params(params)


def render_frozen(scenes: SceneCache, kind: str, active: ActiveFrame, spp: int, seed: int) -> np.ndarray:
    """``mi.render`` of ``active`` as it is set up: H×W×3 linear radiance; a Dr.Jit frozen function
    (one recording per kind, loaded scene and spp, replayed) when ``scenes.frozen``."""
    mi = scenes.mi
    if scenes.frozen:
        img = scenes.frozen_call(f"render/{kind}", _render, active.scene, mi.UInt32(seed), spp, scene=active.scene)
    else:
        img = mi.render(active.scene, spp=spp, seed=seed)
    return np.array(img, dtype=np.float32)


def srgb_encode_grad(linear: np.ndarray, grad_srgb: np.ndarray) -> np.ndarray:
    """d(loss)/d(linear image) from d(loss)/d(sRGB image), at the linear image ``linear``.

    The encoding clips to [0, 1]: saturated pixels pass no gradient.
    """
    x = np.asarray(linear, np.float32)
    inside = (x > 0.0) & (x < 1.0)
    xc = np.clip(x, 1e-8, 1.0)
    deriv = np.where(xc <= 0.0031308, 12.92, 1.055 / 2.4 * np.power(xc, 1 / 2.4 - 1.0))
    return (np.asarray(grad_srgb, np.float32) * deriv * inside).astype(np.float32)


def srgb_decode_deriv(texture_srgb: np.ndarray) -> np.ndarray:
    """d(linear texture)/d(sRGB texture) at the sRGB texture, per texel and channel."""
    t = np.asarray(texture_srgb, np.float32)
    return np.where(t <= 0.04045, 1 / 12.92, 2.4 / 1.055 * np.power((np.maximum(t, 0.04045) + 0.055) / 1.055, 1.4))


def srgb_decode_grad(texture_srgb: np.ndarray, grad_linear: np.ndarray, deriv: np.ndarray | None = None) -> np.ndarray:
    """d(loss)/d(sRGB texture) from d(loss)/d(linear texture), at the sRGB texture (``deriv``: its
    :func:`srgb_decode_deriv`, when the caller holds it)."""
    deriv = srgb_decode_deriv(texture_srgb) if deriv is None else deriv
    return (np.asarray(grad_linear, np.float32) * deriv).astype(np.float32)


def texture_gradient(scenes: SceneCache, index: int, texture_srgb: np.ndarray, grad_linear_image: np.ndarray,
                     spp: int, seed: int, seed_grad: int, conditions: Any = None) -> np.ndarray:
    """Mitsuba's backward pass of frame ``index``'s gradient scene, seeded with an image gradient.

    ``grad_linear_image`` is d(loss)/d(linear image) (H×W×3); returns
    d(loss)/d(sRGB texture) (H×W×3). The gradient is that of the render with
    ``seed_grad`` (what ``mi.render(..., seed, seed_grad)`` back-propagates);
    ``seed`` only names the primal render it pairs with and must differ.
    ``conditions``: the camera and light moved as for the simulator's frame.
    """
    import drjit as dr

    if seed == seed_grad:
        raise RenderError(f"seed_grad must differ from seed (both {seed}): prb needs decorrelated samples")
    mi = scenes.mi
    active = scenes.frame("grad", index, conditions)
    tex = _linear_texture(scenes, active, texture_srgb)
    w, h = (int(v) for v in active.params["sensor.film.crop_size"])
    g = np.ascontiguousarray(grad_linear_image, dtype=np.float32)
    if g.shape != (h, w, 3):
        raise RenderError(f"image gradient has shape {g.shape}, the render's is {(h, w, 3)}")
    # Not frozen: Dr.Jit 1.5 corrupts memory when a frozen function runs a backward pass
    # through scene parameters (seen here as "corrupted size vs. prev_size" at teardown).
    dr.enable_grad(tex)
    active.params[active.texture_key] = tex
    update_params(active.params)
    scene = active.scene
    scene.integrator().render_backward(scene, active.params, mi.TensorXf(g), seed=seed_grad, spp=spp)
    grad_lin = np.array(dr.grad(tex), dtype=np.float32)
    dr.disable_grad(tex)
    return srgb_decode_grad(texture_srgb, grad_lin)


def _render(scene: Any, seed: Any, spp: int) -> Any:
    import mitsuba as mi

    return mi.render(scene, spp=spp, seed=seed)

