"""A medium's look without its cost: an attack window rendered clear, mapped into the fog (``media: auto``).

In fog, and in the haze of rain and snow, the simulation scene is path traced
through a homogeneous medium (``volpath``), and a pixel of medium costs 3–5× a
clear one (docs/performance.md, "Media"). During the ATTACK only, a window of
such a frame is instead rendered by the frame's gradient scene (``prb``,
direct light, no medium: the scene whose captured transport carries the
gradient back) and mapped into the medium's look by a per-pixel affine model::

    V(t) ≈ V_base + α ⊙ (G(t) − G(t_base))

``V_base`` the frame's volpath base (the scene's own texture ``t_base``),
``G`` the gradient scene's window rendered at one fixed seed (so the base
texture reproduces ``V_base`` exactly), and ``α = k · T(d)``: ``T(d) =
exp(−σt · d)`` the medium's transmittance over the camera-to-surface distance
``d`` of each pixel (rays cast into the gradient scene through pixel centres; the
nearest within the film filter's reach, so that the object's rim pixels take
the object's distance), ``k`` (per colour
channel) the ratio of the light on the object in the medium to the
gradient scene's direct light, fitted once per frame by least squares from two
volpath renders of the window (the base texture and a black one) against the
gradient scene's two: ``V_base − V_black ≈ k · T · (G_base − G_black)`` over
the pixels the texture reaches. The image's derivative in ``G`` is ``α``, so
the image gradient is multiplied by ``α`` before it goes through the
gradient scene's transport (:func:`scale_gradient`). The final evaluation
never uses this: it renders whole frames with the medium.
"""
from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from undream.render.crop import Window
from undream.render.differentiable import render_linear
from undream.render.scene_cache import SceneCache
from undream.scene import environment
from undream.spec import Environment

MODES = ("auto", "exact")
FILTER_REACH = 2  # px: the film's gaussian filter spreads a sample this far (undream.render.crop.PAD)
REACH = 1e-4  # |G_base − G_black| (linear) above which a pixel counts as reached by the texture in the fit


@dataclass(frozen=True)
class MediumModel:
    """One frame's window mapping: ``alpha`` and ``g_base`` are ``rendered.height × rendered.width × 3``."""

    rendered: Window  # the window the clear renders cover (the composited window plus its pad)
    alpha: np.ndarray  # k · T(d) per pixel and channel
    g_base: np.ndarray  # the gradient scene's window with the base texture at ``seed`` (linear)
    seed: int  # the seed of every gradient-scene window render of this frame
    gain: tuple[float, float, float]  # k per channel

    def window(self, g_new: np.ndarray) -> np.ndarray:
        """The medium's window for the gradient scene's window ``g_new`` (same seed) as a change of
        the base: ``α ⊙ (g_new − g_base)``, to add to the base's window (linear radiance)."""
        return self.alpha * (np.asarray(g_new, np.float32) - self.g_base)


def transmittance(distance: np.ndarray, sigma_t: float) -> np.ndarray:
    """``exp(−σt · d)`` for distances in metres (inf: 0), extinction ``sigma_t`` in 1/m."""
    d = np.asarray(distance, np.float64)
    return np.where(np.isfinite(d), np.exp(-float(sigma_t) * np.where(np.isfinite(d), d, 0.0)), 0.0)


def nearest_within(distance: np.ndarray, px: int) -> np.ndarray:
    """The least of ``distance`` (h×w) within ``px`` pixels of each pixel: the object's distance on its
    rim, where a pixel centre sees what lies behind but the filter brings the object's samples in."""
    from scipy.ndimage import minimum_filter

    return minimum_filter(np.asarray(distance, np.float64), size=2 * px + 1, mode="nearest")


def camera_distance(scenes: SceneCache, index: int, window: Window) -> np.ndarray:
    """Metres from the camera to the first surface of frame ``index``'s gradient scene through each
    pixel centre of ``window`` (``height × width``; inf where the ray meets nothing)."""
    mi = scenes.mi
    active = scenes.frame("grad", index)
    params = active.params
    ox, oy = (int(v) for v in params["sensor.film.crop_offset"])
    cw, ch = (int(v) for v in params["sensor.film.crop_size"])
    ys, xs = np.mgrid[window.y0:window.y1, window.x0:window.x1].astype(np.float32) + 0.5
    pos = mi.Point2f(((xs - ox) / cw).ravel(), ((ys - oy) / ch).ravel())
    sensor = active.scene.sensors()[0]
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = active.scene.ray_intersect(ray)
    t = np.array(si.t, np.float64)
    t[~np.array(si.is_valid(), bool)] = np.inf
    return t.reshape(window.height, window.width)


def fit_gain(dv: np.ndarray, dg: np.ndarray, trans: np.ndarray) -> tuple[float, float, float]:
    """Least-squares ``k`` per channel of ``dv ≈ k · trans · dg`` over the pixels where
    ``|dg| > REACH`` (``dv``, ``dg``: h×w×3 differences of two textures' renders; ``trans``: h×w);
    1 for a channel that no pixel reaches."""
    x = np.asarray(dg, np.float64) * np.asarray(trans, np.float64)[..., None]
    reached = np.abs(np.asarray(dg)) > REACH
    out = []
    for c in range(3):
        xc, yc = x[..., c][reached[..., c]], np.asarray(dv, np.float64)[..., c][reached[..., c]]
        den = float(xc @ xc)
        out.append(float(xc @ yc) / den if den > 0 else 1.0)
    return out[0], out[1], out[2]


def fit_medium(scenes: SceneCache, index: int, rendered: Window, texture_srgb: np.ndarray, sigma_t: float,
               spp: int, seed: int) -> MediumModel:
    """Frame ``index``'s :class:`MediumModel` over ``rendered`` with the base texture ``texture_srgb``
    (sRGB): the volpath and gradient-scene windows of the base and of a black texture at ``seed``,
    the distances, the gain (four window renders, once per frame)."""
    black = np.zeros_like(np.asarray(texture_srgb, np.float32))
    v_base = render_linear(scenes, index, texture_srgb, spp, seed, window=rendered)
    v_black = render_linear(scenes, index, black, spp, seed, window=rendered)
    g_base = render_linear(scenes, index, texture_srgb, spp, seed, kind="grad", window=rendered)
    g_black = render_linear(scenes, index, black, spp, seed, kind="grad", window=rendered)
    trans = transmittance(nearest_within(camera_distance(scenes, index, rendered), FILTER_REACH), sigma_t)
    gain = fit_gain(v_base - v_black, g_base - g_black, trans)
    alpha = (trans[..., None] * np.asarray(gain, np.float64)).astype(np.float32)
    return MediumModel(rendered, alpha, g_base, seed, gain)


def render_clear(scenes: SceneCache, index: int, model: MediumModel, texture_srgb: np.ndarray, spp: int) -> np.ndarray:
    """The gradient scene's window of ``model`` with ``texture_srgb`` at the model's seed (linear)."""
    return render_linear(scenes, index, texture_srgb, spp, model.seed, kind="grad", window=model.rendered)


def scale_gradient(model: MediumModel, inner: Window, grad_linear_image: np.ndarray) -> np.ndarray:
    """d(loss)/d(gradient-scene image) from d(loss)/d(frame) (H×W×3, linear) where the frame's
    ``inner`` window is ``V_base + α ⊙ (G − G_base)``: ``α ⊙ g`` inside it, 0 elsewhere (the base)."""
    g = np.asarray(grad_linear_image, np.float32)
    out = np.zeros_like(g)
    out[inner.slices] = g[inner.slices] * model.alpha[inner.within(model.rendered)]
    return out


def sigma_t_of(env: Environment) -> float | None:
    """The extinction (1/m) of the simulation scene's medium under ``env``, None without one."""
    if not environment.has_medium(env):
        return None
    return float(environment.HAZE.get(env.weather, env.fog_density))
