"""The ``v3`` data distribution of the bundled victims: ``v2`` with plain, unsaturated objects.

``v2`` (:mod:`undream.training.distribution_v2`) dresses every object in a
random texture whose colours are drawn uniformly in the sRGB cube: a
plain grey, white or black object (an untextured one, as every scene's
default texture is) almost never occurs (a solid texture in one image of
five, and a colour whose channels lie within 0.1 of each other in about one
solid of 36). Its victims learned to read the object's shape from the
contrast of a coloured texture, and misread a plain grey trash bin against
asphalt, wet grass or a night sky even where they read a textured one.

``v3`` draws everything as ``v2`` does (camera height, ground distance,
azimuth, field of view, look-at shift, weather, background, time of day,
the same bands and the same held-out rule), except the texture: with
probability :data:`~undream.training.textures.PLAIN_SHARE` a ``plain`` one
(:func:`~undream.training.textures.plain_recipe`: any hue, HSV saturation
0–0.25, value 0.03–0.97 in sRGB), else a ``v2`` texture. Plain textures
occur in both splits (textures are not banded).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from undream.spec import Sequence
from undream.training import distribution_v2 as v2
from undream.training.textures import texture_recipe_v3

NAME = "v3"
BANDS_V3 = v2.BANDS_V2  # the same camera and environment, banded the same way
WEATHER_WEIGHTS_V3 = v2.WEATHER_WEIGHTS_V2
COVERAGE = v2.COVERAGE
REPORTED_BANDS = v2.REPORTED_BANDS
SampleParamsV3 = v2.SampleParamsV2


def sample_params(rng: np.random.Generator, split: str, label: int, name: str,
                  sphere: tuple[np.ndarray, float]) -> SampleParamsV3:
    """Draw one image's parameters for ``split`` as :func:`.distribution_v2.sample_params`
    does, with a :func:`~undream.training.textures.texture_recipe_v3` texture."""
    return v2.sample_params(rng, split, label, name, sphere, texture=texture_recipe_v3)


def sample_frame(p: SampleParamsV3, sphere: tuple[np.ndarray, float], size: int, seed: int) -> Sequence:
    """The one-frame :class:`Sequence` of a sample (:func:`.distribution_v2.sample_frame`)."""
    return v2.sample_frame(p, sphere, size, seed)


def banded_values(params: dict[str, Any]) -> dict[str, float]:
    """The :data:`BANDS_V3` values of one image's parameters (a label record's ``params``)."""
    return v2.banded_values(params)
