"""The ``blender`` simulator: Cycles frames from a render server in Blender's own Python.

``bpy`` 5.0.1 needs numpy < 2 while undream runs on numpy 2, and Blender is
a process-wide singleton with its own thread pool, so Cycles lives in a
separate interpreter (``.venv-blender``, made by ``deploy/setup.sh``) and a
separate process: :mod:`undream.sim.blender_server`, started on the first
render, loads the scene directory once and serves frames over a pipe
(:mod:`undream.sim.blender_protocol`). The interpreter is
``$UNDREAM_BLENDER_PYTHON`` or ``.venv-blender/bin/python`` next to the
undream package.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import weakref
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from undream.color import srgb_to_linear
from undream.errors import RenderError
from undream.sim import register_backend
from undream.sim.blender_protocol import ProtocolError, read_message, write_message

PYTHON_ENV = "UNDREAM_BLENDER_PYTHON"
THREADS_ENV = "UNDREAM_BLENDER_THREADS"
PACKAGE_DIR = Path(__file__).resolve().parents[1]  # .../undream


def blender_python() -> Path:
    """The interpreter that has ``bpy``: ``$UNDREAM_BLENDER_PYTHON`` or ``<repo>/.venv-blender/bin/python``."""
    env = os.environ.get(PYTHON_ENV)
    return Path(env) if env else PACKAGE_DIR.parent / ".venv-blender" / "bin" / "python"


@lru_cache(maxsize=4)
def _check(python: Path) -> None:
    hint = f"run ./deploy/setup.sh or set {PYTHON_ENV}"
    if not python.is_file():
        raise RenderError(f"sim: blender needs Blender's Python (bpy 5.0.1): {python} not found; {hint}")
    probe = subprocess.run([str(python), "-c", "import bpy"], capture_output=True, text=True, timeout=120)
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        raise RenderError(f"sim: blender: {python} cannot import bpy ({last}); {hint}")


def check_blender(python: Path | None = None) -> None:
    """Raise a one-line :class:`RenderError` unless Blender's Python exists and imports ``bpy`` (~1 s once)."""
    _check(Path(python) if python else blender_python())


def _import_root() -> Path:
    """A folder holding only a link to the undream package, for the server's ``PYTHONPATH``.

    Not the package's parent itself: in a non-editable install that is
    undream's site-packages, whose numpy 2 would shadow Blender's numpy 1.
    """
    root = Path(tempfile.mkdtemp(prefix="undream-bpy-path-"))
    (root / "undream").symlink_to(PACKAGE_DIR, target_is_directory=True)
    return root


@register_backend("blender")
class BlenderSimulator:
    """Renders frames of ``scene_dir`` with Cycles (CPU) through a lazily started render server.

    ``threads``: Cycles' CPU threads (default ``$UNDREAM_BLENDER_THREADS`` or
    all cores); ``python``: Blender's interpreter (default :func:`blender_python`).
    """

    name = "blender"

    def __init__(self, scene_dir: Path, threads: int | None = None, python: str | Path | None = None,
                 **_shared: Any):
        self.scene_dir = Path(scene_dir).resolve()
        self.python = Path(python) if python else blender_python()
        self.threads = int(threads if threads is not None else os.environ.get(THREADS_ENV, 0))
        self._proc: subprocess.Popen | None = None
        self._root: Path | None = None
        self._finalizer: weakref.finalize | None = None
        self._versions: dict[str, str] = {}
        check_blender(self.python)

    def _start(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        self._root = root = _import_root()
        env = {**os.environ, "PYTHONPATH": str(root), "PYTHONNOUSERSITE": "1"}
        cmd = [str(self.python), "-m", "undream.sim.blender_server", str(self.scene_dir),
               "--threads", str(self.threads)]
        with open(root / "server.log", "wb") as log:  # Blender's own output, for errors
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
                                          env=env, cwd=str(root))
        # Stops the server when this backend is garbage-collected or the process exits.
        self._finalizer = weakref.finalize(self, _shutdown, self._proc, root)
        header, _ = self._receive("starting the Cycles server")
        self._versions = {str(k): str(v) for k, v in header.get("versions", {}).items()}
        return self._proc

    def _receive(self, doing: str) -> tuple[dict[str, Any], np.ndarray | None]:
        assert self._proc is not None and self._proc.stdout is not None
        try:
            header, array = read_message(self._proc.stdout)
        except ProtocolError as err:
            try:
                code: int | None = self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                code = None
            last = self._last_log_line()
            self.close()
            raise RenderError(f"sim: blender: {doing}: the server ended ({err}; exit code {code}; "
                              f"last output: {last})") from None
        if "error" in header:
            raise RenderError(f"sim: blender: {doing}: {header['error']}")
        return header, array

    def _last_log_line(self) -> str:
        try:
            lines = (self._root / "server.log").read_text(errors="replace").strip().splitlines()  # type: ignore[operator]
        except (OSError, TypeError):
            return "none"
        return lines[-1][:300] if lines else "none"

    def render(self, index: int, texture_srgb: np.ndarray, spp: int, seed: int,
               conditions: Any = None) -> np.ndarray:
        """Frame ``index`` with ``texture_srgb`` (H×W×3 sRGB in [0, 1]): H×W×3 linear radiance (float32).

        ``conditions`` (EOT) cannot be applied in Cycles: RenderError when given.
        """
        if conditions is not None:
            raise RenderError("sim: blender cannot move the camera and light per render (eot); use sim: mitsuba")
        tex = np.asarray(texture_srgb, dtype=np.float32)
        if tex.ndim != 3 or tex.shape[2] != 3 or not np.isfinite(tex).all():
            raise RenderError(f"texture must be a finite H×W×3 array, got shape {tex.shape}")
        proc = self._start()
        assert proc.stdin is not None
        try:
            write_message(proc.stdin, {"cmd": "render", "index": int(index), "spp": int(spp),
                                       "seed": int(seed) % (2**31 - 1)}, srgb_to_linear(tex))
        except (BrokenPipeError, OSError) as err:
            self.close()
            raise RenderError(f"sim: blender: frame {index}: the server is gone ({err})") from None
        _, img = self._receive(f"frame {index}")
        if img is None:
            raise RenderError(f"sim: blender: frame {index}: the server sent no image")
        return np.array(img, dtype=np.float32)

    def coverage(self, index: int, spp: int = 16) -> np.ndarray:
        """The object's visible coverage in Cycles (H×W float32 in [0, 1]); its mask is ``coverage > 0.5``."""
        proc = self._start()
        assert proc.stdin is not None
        write_message(proc.stdin, {"cmd": "coverage", "index": int(index), "spp": int(spp)})
        _, img = self._receive(f"coverage of frame {index}")
        if img is None:
            raise RenderError(f"sim: blender: frame {index}: the server sent no coverage")
        return np.array(img, dtype=np.float32)

    def versions(self) -> dict[str, str]:
        self._start()
        return dict(self._versions)

    def close(self) -> None:
        """Ask the server to quit and wait for it (killed after 10 s); a later render starts a new one."""
        proc, root, self._proc, self._root = self._proc, self._root, None, None
        if self._finalizer is not None:
            self._finalizer.detach()
            self._finalizer = None
        _shutdown(proc, root)


def _shutdown(proc: subprocess.Popen | None, root: Path | None) -> None:
    """Stop a render server (``quit``, then kill after 10 s) and remove its import folder."""
    if root is not None:
        shutil.rmtree(root, ignore_errors=True)
    if proc is None or proc.poll() is not None:
        return
    try:
        assert proc.stdin is not None
        write_message(proc.stdin, {"cmd": "quit"})
        proc.stdin.close()
        proc.wait(timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
