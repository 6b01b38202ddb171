"""undream: adversarial textures for 3D objects, judged in the simulator they live in.

The public API is imported lazily so that ``import undream`` stays cheap and
chooses no Mitsuba variant.
"""
from __future__ import annotations

import importlib
from typing import Any

from undream.errors import (
    AssetError,
    BridgeError,
    RenderError,
    SpecError,
    StoreError,
    UndreamError,
    VictimError,
)

__version__ = "0.1.0"

_LAZY = {
    "init_scene": "undream.scenedir.init",
    "load_victim": "undream.victims",
    "load_sequence": "undream.spec",
    "save_sequence": "undream.spec",
    "sequence_from_file": "undream.scene.sources",
}

__all__ = ["AssetError", "BridgeError", "RenderError", "SpecError", "StoreError",
           "UndreamError", "VictimError", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'undream' has no attribute {name!r}")
