"""Disjoint-band held-out splits: a parameter range cut into equal bands that alternate
between ``train`` (even bands) and ``test`` (odd bands).

A band table maps a parameter name to ``(low, high, width)`` in the parameter's
own unit; band ``k`` of a value is ``floor((value - low) / width)``. With an odd
number of bands every test band lies between two training bands, so the held-out
set interpolates and never extrapolates.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

SPLITS = ("train", "test")
Bands = dict[str, tuple[float, float, float]]


def record_values(params: dict[str, Any], camera: tuple[str, ...]) -> dict[str, float]:
    """The banded values of one image's parameters (a label record's ``params``): the ``camera``
    fields as they are, the fog density, and the time of day as ``day_time_h`` or, at night,
    ``night_time_h`` (hours after midnight counted from 24)."""
    env = params["environment"]
    t = env["time_of_day"]
    out = {k: float(params[k]) for k in camera}
    out["fog_density"] = float(env["fog_density"])
    if env["weather"] == "night":
        out["night_time_h"] = t + 24.0 if t < 12.0 else t
    else:
        out["day_time_h"] = t
    return out


def band_index(bands: Bands, param: str, value: float) -> int:
    """The band of ``value`` for the parameter ``param`` of ``bands``."""
    lo, _, width = bands[param]
    return int(math.floor((value - lo) / width + 1e-9))


def band_count(bands: Bands, param: str) -> int:
    lo, hi, width = bands[param]
    return int(round((hi - lo) / width))


def band_label(bands: Bands, param: str, value: float) -> str:
    """The band of ``value`` as its interval, e.g. ``[0.8, 1.1)``."""
    lo, _, width = bands[param]
    k = band_index(bands, param, value)
    return f"[{lo + k * width:g}, {lo + (k + 1) * width:g})"


def split_of(bands: Bands, param: str, value: float) -> str:
    """Which split a value of the banded parameter ``param`` belongs to."""
    return SPLITS[band_index(bands, param, value) % 2]


def draw_banded(rng: np.random.Generator, bands: Bands, param: str, split: str) -> float:
    """A value of ``param`` uniform over the bands of ``split``."""
    lo, _, width = bands[param]
    choices = [k for k in range(band_count(bands, param)) if k % 2 == SPLITS.index(split)]
    k = int(rng.choice(choices))
    # stay clear of the band edges so that float rounding cannot move a value across
    return lo + (k + rng.uniform(0.001, 0.999)) * width
