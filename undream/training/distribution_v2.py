"""The ``v2`` data distribution of the bundled victims: the camera placed on the ground plan.

Where ``v1`` (:mod:`undream.training.dataset`) orbits the camera at a
random elevation and sets its distance from the object's size in the frame,
``v2`` draws what a camera in a street has: its HEIGHT above the ground
(0.2–3.5 m), its horizontal DISTANCE from the object's vertical axis
(1.5–8 m), its azimuth about the object and its field of view, and looks at
the object's centre (moved by a small off-centre shift). Every background of
:data:`undream.spec.model.BACKGROUNDS` and every weather of
:data:`undream.spec.model.WEATHERS` occurs, at times of day across the day.

Field of view: drawn from 12–66° but redrawn (with the distance, without
rendering) until the object's bounding sphere spans :data:`COVERAGE` of the
frame width (angular diameter / field of view), so that a traffic cone 8 m
away is seen through a narrow lens (≤ about 26°) and a car 2.5 m away through a
wide one; a camera inside the object's bounding sphere is redrawn the same
way. The image is then checked for visible pixels like ``v1``'s.

Held-out split: every parameter of :data:`BANDS_V2` alternates between train
and test bands (see :mod:`undream.training.bands`); each has an odd number of
bands (azimuth is cyclic), so the test bands lie between training bands.
Angles in degrees, lengths in metres, world +Y up, the ground at y = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from undream.errors import DatasetError
from undream.scene.poses import look_at, object_pose, yaw_rotation
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec.model import BACKGROUNDS
from undream.training.bands import Bands, draw_banded, record_values, split_of
from undream.training.textures import texture_recipe

NAME = "v2"
BANDS_V2: Bands = {
    "azimuth_deg": (0.0, 360.0, 30.0),  # camera around the object, 0 = in front of it (cyclic)
    "height_m": (0.2, 3.5, 0.3),  # camera above the ground
    "distance_m": (1.5, 8.0, 0.5),  # camera to the object's vertical axis, horizontally
    "fov_deg": (12.0, 66.0, 6.0),  # horizontal field of view
    "fog_density": (0.01, 0.06, 0.01),  # 1/m (used in fog only)
    "day_time_h": (6.5, 19.5, 1.0),  # time_of_day, weathers other than night
    "night_time_h": (20.0, 29.0, 1.0),  # time_of_day at night; hours after midnight count from 24
}
WEATHER_WEIGHTS_V2 = {"clear": 0.2, "cloudy": 0.15, "night": 0.15, "fog": 0.2, "rain": 0.15, "snow": 0.15}
COVERAGE = (0.25, 1.0)  # bounding-sphere angular diameter / horizontal field of view
MAX_SHIFT = 0.3  # look-at shift, at most this share of the free half frame
MIN_VISIBLE_SHARE = 60 / 64**2  # of the frame's pixels: v1's 60 pixels of a 64-pixel image
MAX_POSE_DRAWS = 500  # (distance, fov) draws before giving up: geometry only, no rendering
# The camera parameters that evaluation reports band by band.
REPORTED_BANDS = ("height_m", "distance_m")


@dataclass(frozen=True)
class SampleParamsV2:
    """Everything random about one ``v2`` image (angles in degrees, lengths in metres)."""

    label: int
    name: str
    yaw_deg: float  # object yaw in the world
    azimuth_deg: float  # camera azimuth relative to the object's front (+Z), in [0, 360)
    height_m: float  # camera above the ground
    distance_m: float  # camera to the object's vertical axis, horizontally
    fov_deg: float
    coverage: float  # bounding-sphere angular diameter / fov (follows from the above)
    shift: tuple[float, float]  # look-at offset, fractions of the half frame (x, y)
    environment: Environment
    texture: dict[str, Any] = field(default_factory=dict)  # kind and its parameters


def min_visible_pixels(size: int) -> int:
    """Pixels the object must cover (by more than half) in a ``size``×``size`` image: 60 at 64 px."""
    return max(1, round(MIN_VISIBLE_SHARE * size * size))


def _environment(rng: np.random.Generator, split: str) -> Environment:
    weather = str(rng.choice(list(WEATHER_WEIGHTS_V2), p=list(WEATHER_WEIGHTS_V2.values())))
    if weather == "night":
        t = draw_banded(rng, BANDS_V2, "night_time_h", split) % 24.0
    else:
        t = draw_banded(rng, BANDS_V2, "day_time_h", split)
    return Environment(weather=weather, time_of_day=t, background=str(rng.choice(BACKGROUNDS)),
                       sun_max_elevation_deg=float(rng.uniform(35.0, 75.0)),
                       fog_density=draw_banded(rng, BANDS_V2, "fog_density", split))


def _eye(centre: np.ndarray, azimuth_rad: float, height: float, distance: float) -> np.ndarray:
    return np.array([centre[0] + distance * math.sin(azimuth_rad), height,
                     centre[2] + distance * math.cos(azimuth_rad)])


def coverage_of(centre: np.ndarray, radius: float, eye: np.ndarray, fov_deg: float) -> float:
    """Angular diameter of the sphere (``centre``, ``radius``) seen from ``eye`` over the
    field of view; ``inf`` when the eye is inside the sphere."""
    d = float(np.linalg.norm(eye - centre))
    if d <= radius * 1.05:
        return math.inf
    return 2.0 * math.degrees(math.asin(radius / d)) / fov_deg


def sample_params(rng: np.random.Generator, split: str, label: int, name: str,
                  sphere: tuple[np.ndarray, float],
                  texture: Callable[[np.random.Generator], dict[str, Any]] = texture_recipe) -> SampleParamsV2:
    """Draw one image's parameters for ``split``; ``sphere`` is the object's bounding
    sphere (centre in the object frame, radius; metres); ``texture`` draws the texture
    recipe, last (``v3`` passes its own)."""
    yaw = float(rng.uniform(0.0, 360.0))
    env = _environment(rng, split)
    azimuth = draw_banded(rng, BANDS_V2, "azimuth_deg", split)
    height = draw_banded(rng, BANDS_V2, "height_m", split)
    centre = yaw_rotation(yaw).apply(sphere[0])
    az = math.radians(yaw + azimuth)
    for _ in range(MAX_POSE_DRAWS):
        distance = draw_banded(rng, BANDS_V2, "distance_m", split)
        fov = draw_banded(rng, BANDS_V2, "fov_deg", split)
        cov = coverage_of(centre, sphere[1], _eye(centre, az, height, distance), fov)
        if COVERAGE[0] <= cov <= COVERAGE[1]:
            break
    else:
        raise DatasetError(f"v2 sample of {name}: no distance and field of view framed it in "
                           f"{MAX_POSE_DRAWS} draws")
    room = MAX_SHIFT * (1.0 - min(cov, 1.0))
    return SampleParamsV2(
        label=label, name=name, yaw_deg=yaw, azimuth_deg=azimuth, height_m=height, distance_m=distance,
        fov_deg=fov, coverage=cov, shift=(float(rng.uniform(-room, room)), float(rng.uniform(-room, room))),
        environment=env, texture=texture(rng))


def sample_frame(p: SampleParamsV2, sphere: tuple[np.ndarray, float], size: int, seed: int) -> Sequence:
    """A one-frame :class:`Sequence` of the sample (object at the origin, yawed; ``size`` px square)."""
    rot = yaw_rotation(p.yaw_deg)
    centre = rot.apply(sphere[0])
    eye = _eye(centre, math.radians(p.yaw_deg + p.azimuth_deg), p.height_m, p.distance_m)
    base = look_at(eye, centre)
    span = float(np.linalg.norm(eye - centre)) * math.tan(math.radians(p.fov_deg) / 2.0)
    target = centre + span * (p.shift[0] * base[:3, 0] + p.shift[1] * base[:3, 1])
    cam = Camera(Transform.from_rows(look_at(eye, target)), p.fov_deg, (size, size))
    obj = object_pose((0.0, 0.0, 0.0), rot)
    frame = Frame(index=0, camera=cam, object_to_world=Transform.from_rows(obj), environment=p.environment)
    asset = Asset(name="object", mesh=f"builtin:{p.name}", texture=TextureParam(resolution=(size, size)))
    return Sequence(name="sample", asset=asset, frames=(frame,), seed=seed)


def banded_values(params: dict[str, Any]) -> dict[str, float]:
    """The :data:`BANDS_V2` values of one image's parameters (a label record's ``params``)."""
    return record_values(params, ("azimuth_deg", "height_m", "distance_m", "fov_deg"))


def splits_of(params: dict[str, Any]) -> set[str]:
    """The splits that the banded values of ``params`` belong to (one for a valid image)."""
    return {split_of(BANDS_V2, k, v) for k, v in banded_values(params).items()}

