"""Blender's own interpreter: where it is, whether it imports ``bpy``, how to start undream code in it.

``bpy`` 5.0.1 needs Python 3.11 and numpy < 2 while undream runs on numpy 2,
so everything that imports ``bpy`` runs in a separate interpreter
(``.venv-blender``, made by ``deploy/setup.sh``) as a subprocess: the Cycles
render server (:mod:`undream.sim.blender_server`) and the ``.blend`` exporter
(:mod:`undream.bridge.blender_export`). The interpreter is the one the caller
passes (the edge reads ``$UNDREAM_BLENDER_PYTHON``,
:class:`undream.settings.LocalSettings`) or ``.venv-blender/bin/python`` next
to the undream package. Standard library only.
"""
from __future__ import annotations

import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Mapping

PYTHON_ENV = "UNDREAM_BLENDER_PYTHON"
PACKAGE_DIR = Path(__file__).resolve().parents[1]  # .../undream
HINT = f"run ./deploy/setup.sh or set {PYTHON_ENV}"


def blender_python(python: str | Path | None = None) -> Path:
    """The interpreter that has ``bpy``: ``python`` (``$UNDREAM_BLENDER_PYTHON`` at the edge) or
    ``<repo>/.venv-blender/bin/python``."""
    return Path(python) if python else PACKAGE_DIR.parent / ".venv-blender" / "bin" / "python"


@lru_cache(maxsize=4)
def bpy_problem(python: Path) -> tuple[str, str] | None:
    """None when ``python`` imports ``bpy`` (~1 s, once per interpreter); else ``(kind, reason)``.

    ``kind`` is ``"missing"`` (no such file: the reason is the path) or
    ``"broken"`` (the reason is the interpreter's last line of error output).
    """
    if not python.is_file():
        return "missing", str(python)
    probe = subprocess.run([str(python), "-c", "import bpy"], capture_output=True, text=True, timeout=120)
    if probe.returncode != 0:
        return "broken", (probe.stderr.strip().splitlines() or ["no output"])[-1]
    return None


def import_root() -> Path:
    """A new folder holding only a link to the undream package, for Blender's ``PYTHONPATH``.

    Not the package's parent itself: in a non-editable install that is
    undream's site-packages, whose numpy 2 would shadow Blender's numpy 1.
    The caller removes it when done.
    """
    root = Path(tempfile.mkdtemp(prefix="undream-bpy-path-"))
    (root / "undream").symlink_to(PACKAGE_DIR, target_is_directory=True)
    return root


def blender_env(root: Path, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment for undream code in Blender's interpreter (``root`` from :func:`import_root`):
    ``base`` (the edge passes its environment, :attr:`undream.settings.LocalSettings.child_env`;
    None: nothing else) with undream's ``PYTHONPATH`` and no user site-packages."""
    return {**(base or {}), "PYTHONPATH": str(root), "PYTHONNOUSERSITE": "1"}
