"""Print-and-capture EOT: what printing a texture and photographing it may do, drawn per frame.

A run's ``eot_print`` block (:class:`undream.spec.physical.PrintEotConfig`) bounds each change;
:func:`draw_print` draws one :class:`PrintDraw` per (run seed, iteration, frame index) from those
numbers alone (no generator at import; a retried or resumed iteration draws the same), so the
texture is optimised for a distribution of prints and captures around the one it will be judged
as (the expectation over transformations of Athalye et al., 2018, as Sharif et al. 2016 and
Brown et al. 2017 use it for printed patches).

The texture's side (:func:`print_texture`, torch, differentiable: the gradient the renderer gives
w.r.t. the printed texture is carried back to the texture by autograd, :func:`texture_vjp`), on
sRGB values in [0, 1], in this order: gamma ``x ** γ``; contrast ``(x − ½)·c + ½``; saturation
``Y + s·(x − Y)`` with ``Y`` the Rec. 709 luma of the sRGB values; brightness ``+ b``; clamp to
[0, 1]; a print blur, Gaussian of σ texels (:func:`undream.attacks.base.blur_gradient`, edges
repeated). The camera's side (:func:`capture_noise`): Gaussian noise of standard deviation
``noise`` (sRGB 0–1) added to the rendered frame before the victim sees it, clipped to [0, 1].
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from undream.attacks.base import blur_gradient

PRINT_STREAM = 0x9217  # keeps these random numbers apart from every other stream of (seed, iteration, frame)
LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 weights, applied to the sRGB values
GAMMA_FLOOR = 1e-6  # x ** γ is evaluated at no less than this (its slope is unbounded at 0 for γ < 1)


@dataclass(frozen=True)
class PrintDraw:
    """One frame's print and capture: ``brightness`` offset (sRGB 0–1), ``contrast`` and
    ``saturation`` factors, ``gamma`` exponent, ``blur`` σ (texels), camera ``noise`` σ (sRGB 0–1)
    and the seed of that frame's noise image."""

    brightness: float = 0.0
    contrast: float = 1.0
    saturation: float = 1.0
    gamma: float = 1.0
    blur: float = 0.0
    noise: float = 0.0
    noise_seed: int = 0

    @property
    def changes_texture(self) -> bool:
        return (self.brightness, self.contrast, self.saturation, self.gamma, self.blur) != (0.0, 1.0, 1.0, 1.0, 0.0)


def draw_print(config: Any, seed: int, iteration: int, index: int) -> PrintDraw | None:
    """The print and capture of frame ``index`` at ``iteration`` of a run of ``seed`` under
    ``config`` (a :class:`undream.spec.physical.PrintEotConfig`; None: none, and None is returned).
    Brightness uniform in ±``brightness``; contrast and saturation uniform in 1 ± their value;
    gamma ``exp(u)``, ``u`` uniform in ±``gamma``; blur σ uniform in [0, ``blur``]; noise σ ``noise``."""
    if config is None:
        return None
    rng = np.random.default_rng([seed, iteration, index, PRINT_STREAM])
    u = rng.uniform(-1.0, 1.0, size=5)
    return PrintDraw(brightness=float(u[0] * config.brightness), contrast=float(1.0 + u[1] * config.contrast),
                     saturation=float(1.0 + u[2] * config.saturation),
                     gamma=float(math.exp(u[3] * config.gamma)), blur=float((u[4] + 1.0) / 2.0 * config.blur),
                     noise=float(config.noise), noise_seed=int(rng.integers(0, 2**31 - 1)))


def print_texture(T: torch.Tensor, draw: PrintDraw) -> torch.Tensor:
    """``T`` (H×W×3 sRGB 0–1) as ``draw`` prints it (see the module docstring): H×W×3 in [0, 1]."""
    x = T.clamp(min=GAMMA_FLOOR) ** draw.gamma if draw.gamma != 1.0 else T
    x = (x - 0.5) * draw.contrast + 0.5
    luma = (x * x.new_tensor(LUMA)).sum(dim=-1, keepdim=True)
    x = luma + draw.saturation * (x - luma)
    x = (x + draw.brightness).clamp(0.0, 1.0)
    return blur_gradient(x, draw.blur)


def printed(texture: np.ndarray, draw: PrintDraw | None) -> np.ndarray:
    """:func:`print_texture` of an H×W×3 float array (float32 out); ``texture`` itself without a change."""
    if draw is None or not draw.changes_texture:
        return texture
    with torch.no_grad():
        return print_texture(torch.from_numpy(np.asarray(texture, np.float64)), draw).numpy().astype(np.float32)


def texture_vjp(texture: np.ndarray, draw: PrintDraw | None, grad_printed: np.ndarray) -> np.ndarray:
    """d loss / d texture (H×W×3) from d loss / d printed texture (``grad_printed``) through
    :func:`print_texture` (autograd, float64); ``grad_printed`` itself without a change."""
    if draw is None or not draw.changes_texture:
        return grad_printed
    T = torch.from_numpy(np.asarray(texture, np.float64)).requires_grad_(True)
    (g,) = torch.autograd.grad(print_texture(T, draw), T, torch.from_numpy(np.asarray(grad_printed, np.float64)))
    return g.numpy().astype(np.float32)


def capture_noise(image: np.ndarray, draw: PrintDraw | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The frame ``image`` (H×W×3 sRGB 0–1) with ``draw``'s camera noise added and clipped to [0, 1],
    and where the clip let the noisy value through (H×W×3 bool: d noisy / d image is 1 there, 0
    elsewhere); (``image``, None) without noise."""
    if draw is None or draw.noise <= 0:
        return image, None
    rng = np.random.default_rng([draw.noise_seed, PRINT_STREAM])
    noisy = image + rng.normal(0.0, draw.noise, size=image.shape).astype(image.dtype)
    inside = (noisy >= 0.0) & (noisy <= 1.0)
    return np.clip(noisy, 0.0, 1.0), inside
