"""Loading a Mitsuba scene file and finding the adversarial texture among its parameters."""
from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from undream.color import linear_to_srgb
from undream.errors import RenderError
from undream.render.haze import register as register_haze
from undream.scene.mitsuba_scene import OBJECT_ID


def texture_param_key(params: Any) -> str:
    """The ``mi.traverse`` key of the object's texture data (``object.bsdf...reflectance.data``)."""
    keys = [k for k in params.keys() if k.startswith(f"{OBJECT_ID}.") and k.endswith("reflectance.data")]
    if len(keys) != 1:
        raise RenderError(f"expected one texture parameter under '{OBJECT_ID}.', found {keys}")
    return keys[0]


def load_scene(mi: ModuleType, xml: Path, spp: int, merge: bool = True) -> Any:
    """``mi.load_file`` with errors as one :class:`RenderError` line naming the file.

    ``merge=False`` keeps every shape apart under its own id (Mitsuba otherwise
    merges meshes sharing a BSDF into one named after a memory address). The ``haze``
    integrator a scene in fog, rain or snow names is registered first.
    """
    register_haze(mi)
    try:
        return mi.load_file(str(xml), optimize=merge, spp=spp)
    except Exception as err:  # Mitsuba raises plain RuntimeError / ValueError
        first = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise RenderError(f"{xml}: Mitsuba could not load the scene ({first})") from None


def read_texture_srgb(mi: ModuleType, exr: Path) -> np.ndarray:
    """A scene directory's texture file (linear float EXR) as sRGB H×W×3 float32 in [0, 1]."""
    try:
        linear = np.array(mi.Bitmap(str(exr)), dtype=np.float32)
    except Exception as err:  # Mitsuba raises plain RuntimeError
        raise RenderError(f"{exr}: cannot read the texture ({str(err).strip().splitlines()[-1]})") from None
    return linear_to_srgb(linear)
