"""The versions of the software that made an output, for its ``metadata.json``."""
from __future__ import annotations

import platform
from importlib.metadata import PackageNotFoundError, version
from types import ModuleType

from undream import __version__

PACKAGES = ("numpy", "scipy", "mitsuba", "drjit", "torch", "transformers")


def versions(mi: ModuleType | None = None) -> dict[str, str]:
    """undream's, Python's and each of :data:`PACKAGES`' version.

    Package versions come from the installed distributions' metadata, so
    nothing is imported (``"not installed"`` where one is missing). With
    ``mi`` (the ``mitsuba`` module, variant set) ``variant`` names the
    Mitsuba variant in use.
    """
    out = {"undream": __version__, "python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    if mi is not None:
        out["variant"] = mi.variant()
    return out
