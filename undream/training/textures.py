"""Random textures of the bundled victims' datasets: small JSON-able recipes and their images.

The object in every image wears one, so that the victims learn shapes rather than textures.
:func:`texture_recipe` draws the ``v1`` / ``v2`` textures; :func:`texture_recipe_v3` adds
``plain`` ones (one unsaturated colour: grey, white, black or a muted tint), which the
uniformly drawn colours of the others almost never give.
"""
from __future__ import annotations

import colorsys
import math
from typing import Any

import numpy as np

TEXTURE_KINDS = ("solid", "stripes", "checker", "noise", "mix")
TEXTURE_KINDS_V3 = TEXTURE_KINDS + ("plain",)
PLAIN_SHARE = 0.3  # of v3 textures: plain
PLAIN_VALUE = (0.03, 0.97)  # sRGB value (HSV) of a plain colour
PLAIN_SATURATION = (0.0, 0.25)  # HSV saturation of a plain colour: greys to muted tints


def _colour(rng: np.random.Generator) -> list[float]:
    return [float(v) for v in rng.uniform(0.0, 1.0, 3)]


def texture_recipe(rng: np.random.Generator) -> dict[str, Any]:
    """A random texture as a small JSON-able recipe (see :func:`make_texture`)."""
    kind = str(rng.choice(TEXTURE_KINDS))
    r: dict[str, Any] = {"kind": kind, "colours": [_colour(rng) for _ in range(3)]}
    if kind in ("stripes", "checker", "mix"):
        r["period"] = float(rng.uniform(4.0, 32.0))
        r["angle_deg"] = float(rng.uniform(0.0, 180.0))
    if kind in ("noise", "mix"):
        r["cells"] = int(rng.integers(2, 9))
        r["noise_seed"] = int(rng.integers(2**31))
    return r


def plain_recipe(rng: np.random.Generator) -> dict[str, Any]:
    """A ``plain`` texture: one colour of random hue, HSV saturation in :data:`PLAIN_SATURATION`
    and value in :data:`PLAIN_VALUE` (sRGB), as an untextured or painted object shows."""
    h, s, v = rng.uniform(0.0, 1.0), rng.uniform(*PLAIN_SATURATION), rng.uniform(*PLAIN_VALUE)
    return {"kind": "plain", "colours": [[float(x) for x in colorsys.hsv_to_rgb(h, s, v)]]}


def texture_recipe_v3(rng: np.random.Generator) -> dict[str, Any]:
    """A ``v3`` texture: :func:`plain_recipe` with probability :data:`PLAIN_SHARE`, else a
    :func:`texture_recipe`."""
    return plain_recipe(rng) if rng.uniform() < PLAIN_SHARE else texture_recipe(rng)


def make_texture(recipe: dict[str, Any], size: int = 64) -> np.ndarray:
    """The ``size×size×3`` sRGB [0, 1] texture of a :func:`texture_recipe` (float32)."""
    c = np.asarray(recipe["colours"], dtype=np.float32)
    kind = recipe["kind"]
    if kind in ("solid", "plain"):
        return np.broadcast_to(c[0], (size, size, 3)).astype(np.float32)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    if kind in ("stripes", "checker", "mix"):
        a = math.radians(recipe["angle_deg"])
        u = (xx * math.cos(a) + yy * math.sin(a)) / recipe["period"]
        v = (-xx * math.sin(a) + yy * math.cos(a)) / recipe["period"]
        pat = (np.floor(u) % 2) if kind != "checker" else ((np.floor(u) + np.floor(v)) % 2)
        two = np.where(pat[..., None] > 0, c[0], c[1])
        if kind != "mix":
            return two.astype(np.float32)
    noise = _smooth_noise(np.random.default_rng(recipe["noise_seed"]), recipe["cells"], size)
    if kind == "noise":
        return noise
    w = noise.mean(-1, keepdims=True)  # mix: stripes of two colours, blended into a third by noise
    return ((1 - w) * two + w * c[2]).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, cells: int, size: int) -> np.ndarray:
    """Random colours on a ``cells×cells`` grid, bilinearly upsampled (periodic), sRGB [0, 1]."""
    grid = rng.uniform(0.0, 1.0, (cells, cells, 3)).astype(np.float32)
    t = (np.arange(size, dtype=np.float32) + 0.5) / size * cells - 0.5
    i0 = np.floor(t).astype(int)
    f = (t - i0)[:, None]
    rows = (1 - f[:, :, None]) * grid[i0 % cells] + f[:, :, None] * grid[(i0 + 1) % cells]
    cols = (1 - f.T[:, :, None]) * rows[:, i0 % cells] + f.T[:, :, None] * rows[:, (i0 + 1) % cells]
    return cols.astype(np.float32)
