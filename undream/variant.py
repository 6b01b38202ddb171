"""Choosing a Mitsuba variant, lazily: nothing happens at import time.

Mitsuba's JIT is not fork-safe, so only call :func:`mitsuba` in the process
that renders (a worker child, a CLI command, a test).
"""
from __future__ import annotations

import os
from types import ModuleType

from undream.errors import RenderError

PREFERRED = ("cuda_ad_rgb", "llvm_ad_rgb")


def mitsuba(variant: str | None = None) -> ModuleType:
    """Import Mitsuba with a differentiable RGB variant set and return the module.

    ``variant`` (or ``$UNDREAM_MI_VARIANT``) forces one; otherwise the first of
    ``cuda_ad_rgb``, ``llvm_ad_rgb`` that works is used. A variant already set
    is kept when none is asked for.
    """
    import mitsuba as mi

    wanted = variant or os.environ.get("UNDREAM_MI_VARIANT")
    if wanted is None and mi.variant() is not None:
        return mi
    candidates = (wanted,) if wanted else PREFERRED
    errors = []
    for name in candidates:
        if name not in mi.variants():
            errors.append(f"{name}: not compiled in this mitsuba build")
            continue
        try:
            mi.set_variant(name)
            if name.startswith("cuda"):
                import drjit as dr
                dr.zeros(mi.Float, 1)  # fails here when no GPU/driver is present
            return mi
        except Exception as err:  # mitsuba raises plain ImportError/RuntimeError
            errors.append(f"{name}: {err}")
    raise RenderError("no usable Mitsuba variant (" + "; ".join(errors) +
                      "); the CPU variant needs libLLVM >= 16 (Debian: apt-get install libllvm19)")
