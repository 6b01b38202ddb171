"""Sun, sky, weather and lamps of an :class:`~undream.spec.Environment` as Mitsuba emitters.

Radiometry is in linear RGB, scaled so that a white diffuse surface in full
sun renders a little below 1 (no tone mapping is applied downstream).

Weather presets (both simulators render them from these numbers; the Blender
backend translates the same Mitsuba dictionaries):

- ``clear``: full sun, blue sky; ``cloudy``: sun at 12 %, bright grey sky;
- ``fog``: sun at 45 %, grey sky, a homogeneous medium of ``fog_density``;
- ``night``: a dark blue sky and one point lamp above the object (warm white,
  up and to one side unless ``lamp_offset`` / ``lamp_intensity`` say otherwise);
- ``rain``: sun at 4 %, a dim grey sky, a light haze (:data:`HAZE`) and a
  wet ground (darker: :func:`ground_tint`);
- ``snow``: sun at 15 %, a bright sky, a light haze and a snow-covered
  ground. Falling drops and flakes are not modelled (in either simulator).

A user's environment map (``Environment.envmap``) replaces the sky and the
sun with one ``envmap`` emitter (Mitsuba's frame: +Y up; the map's left edge
looks along −Z, a quarter in along +X, the centre along +Z), ``envmap_scale`` times its radiance,
turned by ``envmap_rotation_deg`` about +Y; the weather keeps its medium,
its ground and its night lamp.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from undream.scene.xml import Mat4
from undream.spec import Environment, sun_direction

SUN_IRRADIANCE = 2.0  # clear-sky sun, W/m² in undream's display-referred units
FOG_ALBEDO = 0.85
HAZE = {"rain": 0.025, "snow": 0.035}  # extinction (1/m) of the haze that rain and snow bring
SNOW_GROUND = ((0.80, 0.82, 0.86), (0.74, 0.76, 0.80))  # linear albedo of the two checks
WET_DARKENING = 0.55  # a wet ground's albedo relative to the dry one


def _rgb(*v: float) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(x) for x in v]}


def _sun_colour(elev_deg: float) -> np.ndarray:
    """Warmer near the horizon (longer air mass)."""
    warm = math.exp(-max(elev_deg, 0.0) / 12.0)
    return np.array([1.0, 0.95 - 0.25 * warm, 0.88 - 0.5 * warm])


def envmap_rotation(degrees: float) -> np.ndarray:
    """4×4 rotation about +Y by ``degrees`` (right-handed: +X turns towards −Z)."""
    a = math.radians(degrees)
    m = np.eye(4)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return m


def emitters(env: Environment, anchor: np.ndarray, envmap_file: str | None = None) -> dict[str, dict[str, Any]]:
    """Emitters for one frame: ``sky`` (constant, or the user's ``envmap``), ``sun`` (directional;
    none with an envmap), ``lamp`` at night.

    ``anchor`` (metres) is where a night lamp stands near: the object's origin.
    ``envmap_file``: the map's path as the scene file names it (``env.envmap`` if not given).
    """
    direction, elev = sun_direction(env)
    day = float(np.clip(math.sin(math.radians(elev)) * 3.0, 0.0, 1.0))  # fades in at sunrise
    out: dict[str, dict[str, Any]] = {}
    if env.envmap is not None:
        out["sky"] = {"type": "envmap", "filename": envmap_file or env.envmap, "scale": float(env.envmap_scale),
                      "to_world": Mat4.of(envmap_rotation(env.envmap_rotation_deg))}
    if env.weather == "night":
        out.setdefault("sky", {"type": "constant", "radiance": _rgb(0.010, 0.013, 0.028)})
        lamp = np.asarray(anchor, float) + np.asarray(env.lamp_offset, float)
        out["lamp"] = {"type": "point", "position": lamp.tolist(), "intensity": _rgb(*env.lamp_intensity)}
        return out
    if env.envmap is not None:
        return out
    sun_scale, sky = {
        "clear": (1.0, np.array([0.26, 0.34, 0.48])),
        "cloudy": (0.12, np.array([0.50, 0.52, 0.56])),
        "fog": (0.45, np.array([0.42, 0.44, 0.47])),
        "rain": (0.04, np.array([0.26, 0.28, 0.31])),
        "snow": (0.15, np.array([0.60, 0.62, 0.66])),
    }[env.weather]
    twilight = 0.08 + 0.92 * float(np.clip((elev + 6.0) / 12.0, 0.0, 1.0))
    out["sky"] = {"type": "constant", "radiance": _rgb(*(sky * twilight))}
    if day > 0.0:
        irr = _sun_colour(elev) * SUN_IRRADIANCE * sun_scale * day
        out["sun"] = {"type": "directional", "direction": [-float(x) for x in direction],
                      "irradiance": _rgb(*irr)}
    return out


def has_medium(env: Environment) -> bool:
    """Whether the simulation scene holds a scattering medium (fog, or rain's and snow's haze)."""
    return env.weather == "fog" or env.weather in HAZE


def fog_medium(env: Environment) -> dict[str, Any]:
    """A homogeneous, grey scattering medium: extinction ``fog_density`` (1/m) in fog, :data:`HAZE` in rain and snow."""
    density = HAZE.get(env.weather, env.fog_density)
    return {"type": "homogeneous", "id": "fog", "sigma_t": float(density),
            "albedo": _rgb(FOG_ALBEDO, FOG_ALBEDO, FOG_ALBEDO), "scale": 1.0}


def ground_tint(env: Environment, colours: tuple[Any, Any]) -> tuple[Any, Any]:
    """The ground's two check colours (linear) under ``env``: snow-covered, wet (darker) or as they are."""
    if env.weather == "snow":
        return SNOW_GROUND
    if env.weather == "rain":
        return tuple(tuple(WET_DARKENING * float(x) for x in c) for c in colours)  # type: ignore[return-value]
    return colours
