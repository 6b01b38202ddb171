"""Expectation over conditions (EOT): small random changes of a frame's camera and light per iteration.

A run's ``eot`` block (:mod:`undream.spec.run`) says how much each iteration
may move the camera and the light away from the frame's own values, so the
texture is optimised for a distribution of conditions around each frame, not
for the frames alone (Athalye et al., 2018). :func:`draw_conditions` draws
one :class:`Conditions` from (run seed, iteration, frame index) only, so any
process draws the same ones and a retried or resumed iteration repeats them;
:func:`jitter_values` turns them into new values of the Mitsuba parameters
that :class:`undream.render.scene_cache.SceneCache` writes into the frame's
scenes (simulation and gradient alike), for that one render.

Units: camera shift in metres (world axes, Y up), turns in degrees (about a
random axis; the camera's in its own frame, the sun's in the world), light
scale a factor on the sun's irradiance and the sky's radiance (an envmap's scale).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

EOT_STREAM = 0xE07  # keeps EOT's random numbers apart from every other stream of (seed, iteration, frame)
CAMERA_KEY, SUN_KEY = "sensor.to_world", "sun.to_world"
LIGHT_KEYS = ("sun.irradiance.value", "sky.radiance.value", "sky.scale", "lamp.intensity.value")  # sky.scale: an envmap


@dataclass(frozen=True)
class Conditions:
    """One draw: camera shift (3,) m, camera and sun rotations (3×3), light factor."""

    camera_shift: np.ndarray
    camera_turn: np.ndarray
    sun_turn: np.ndarray
    light: float


def _turn(rng: np.random.Generator, degrees: float) -> np.ndarray:
    """A rotation by an angle uniform in ±``degrees`` about a uniformly random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * np.radians(rng.uniform(-degrees, degrees))).as_matrix()


def draw_conditions(eot: Mapping[str, float] | None, seed: int, iteration: int, index: int) -> Conditions | None:
    """The conditions of frame ``index`` at ``iteration`` (None when ``eot`` asks for none)."""
    if not eot:
        return None
    rng = np.random.default_rng([seed, iteration, index, EOT_STREAM])
    shift = float(eot.get("camera_shift_m", 0.0))
    scale = float(eot.get("light_scale", 0.0))
    return Conditions(camera_shift=rng.uniform(-shift, shift, size=3),
                      camera_turn=_turn(rng, float(eot.get("camera_turn_deg", 0.0))),
                      sun_turn=_turn(rng, float(eot.get("sun_turn_deg", 0.0))),
                      light=float(rng.uniform(1.0 - scale, 1.0 + scale)))


def _matrix(value: Any) -> np.ndarray:
    m = np.array(value.matrix, dtype=np.float64)
    return m[..., 0] if m.ndim == 3 else m


def jitter_values(mi: Any, params: Any, conditions: Conditions) -> dict[str, Any]:
    """New values of ``params``' camera, sun and light parameters under ``conditions`` (keys it lacks skipped)."""
    out: dict[str, Any] = {}
    keys = set(params.keys())
    if CAMERA_KEY in keys:
        m = _matrix(params[CAMERA_KEY])
        m[:3, :3] = m[:3, :3] @ conditions.camera_turn
        m[:3, 3] += conditions.camera_shift
        out[CAMERA_KEY] = mi.AffineTransform4f(m)
    if SUN_KEY in keys:
        m = _matrix(params[SUN_KEY])
        m[:3, :3] = conditions.sun_turn @ m[:3, :3]
        out[SUN_KEY] = mi.AffineTransform4f(m)
    for key in LIGHT_KEYS:
        if key in keys:
            out[key] = params[key] * conditions.light
    return out
