"""Simulator backends: what renders the frame the victim sees, behind one interface.

The engine asks a backend for frame ``index`` of a scene directory rendered
with texture ``T`` (sRGB H×W×3 in [0, 1]) at ``spp`` samples with ``seed``,
and gets back H×W×3 LINEAR radiance. The gradient always comes from Mitsuba's
gradient scene (:mod:`undream.render.differentiable`), whatever the backend.
Backends register by name; ``mitsuba`` is the embedded default, ``blender``
renders with Cycles (:mod:`undream.sim.blender`), ``unreal`` hands frames to
an Unreal editor through a spool folder (:mod:`undream.sim.unreal`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from undream.errors import RenderError
from undream.settings import LocalSettings


@runtime_checkable
class SimulatorBackend(Protocol):
    """Renders the frames of one scene directory (one instance per process and scene)."""

    name: str

    def render(self, index: int, texture_srgb: np.ndarray, spp: int, seed: int,
               conditions: Any = None) -> np.ndarray:
        """Frame ``index`` with ``texture_srgb`` (H×W×3 sRGB in [0, 1]): H×W×3 linear radiance.

        ``conditions`` (:class:`undream.render.jitter.Conditions`, EOT): the camera and light
        moved for this render; a backend that cannot move them raises RenderError when given
        any (``mitsuba`` can; run configs refuse ``eot`` with other simulators beforehand).
        """
        ...

    def versions(self) -> dict[str, str]:
        """Names and versions of what renders (for metadata.json)."""
        ...


BackendFactory = Callable[..., SimulatorBackend]
_BACKENDS: dict[str, BackendFactory] = {}


def register_backend(name: str) -> Callable[[BackendFactory], BackendFactory]:
    """Class decorator: make a backend available to :func:`make_backend` as ``name``."""
    def add(factory: BackendFactory) -> BackendFactory:
        _BACKENDS[name] = factory
        return factory
    return add


def make_backend(name: str, scene_dir: str | Path, **options) -> SimulatorBackend:
    """The backend ``name`` for the scene directory ``scene_dir``; errors name the valid choices."""
    _load_builtin()
    if name not in _BACKENDS:
        raise RenderError(f"sim: unknown simulator {name!r} (one of {', '.join(sorted(_BACKENDS))})")
    return _BACKENDS[name](Path(scene_dir), **options)


def backend_options(name: str, local: LocalSettings = LocalSettings()) -> dict[str, Any]:
    """The options of backend ``name`` that come from this process's settings (read at the edge)."""
    if name == "blender":
        return {"threads": local.blender_threads, "python": local.blender_python, "env": local.child_env}
    if name == "unreal":
        return {"spool": local.unreal_spool, "timeout_s": local.unreal_timeout_s}
    return {}


def check_simulator(name: str, local: LocalSettings = LocalSettings()) -> None:
    """Raise a one-line :class:`RenderError` unless backend ``name`` can run here (before anything is
    written), with this process's settings ``local`` (Blender's interpreter, Unreal's spool)."""
    _load_builtin()
    if name not in _BACKENDS:
        raise RenderError(f"sim: unknown simulator {name!r} (one of {', '.join(sorted(_BACKENDS))})")
    if name == "blender":
        from undream.sim.blender import check_blender

        check_blender(local.blender_python)
    if name == "unreal":
        from undream.sim.unreal import check_unreal

        check_unreal(local.unreal_spool)


def _load_builtin() -> None:
    from undream.sim import blender, mitsuba, unreal  # noqa: F401  (register 'blender', 'mitsuba', 'unreal')
