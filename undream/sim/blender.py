"""The ``blender`` simulator: Cycles frames from a render server in Blender's own Python.

``bpy`` 5.0.1 needs numpy < 2 while undream runs on numpy 2, and Blender is
a process-wide singleton with its own thread pool, so Cycles lives in a
separate interpreter (``.venv-blender``, made by ``deploy/setup.sh``) and a
separate process: :mod:`undream.sim.blender_server`, started on the first
render, loads the scene directory once and serves frames over a pipe
(:mod:`undream.sim.blender_protocol`). The interpreter is the backend's
``python`` option (``$UNDREAM_BLENDER_PYTHON`` at the edge) or
``.venv-blender/bin/python`` next to the undream package.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import weakref
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from undream.bridge.blender_python import HINT, blender_env, blender_python, bpy_problem, import_root
from undream.color import srgb_to_linear
from undream.errors import RenderError
from undream.sim import register_backend
from undream.sim.blender_protocol import ProtocolError, read_message, write_message


def check_blender(python: str | Path | None = None) -> None:
    """Raise a one-line :class:`RenderError` unless Blender's Python (``python``, default
    :func:`blender_python`'s) exists and imports ``bpy`` (~1 s once)."""
    python = blender_python(python)
    problem = bpy_problem(python)
    if problem is None:
        return
    kind, reason = problem
    if kind == "missing":
        raise RenderError(f"sim: blender needs Blender's Python (bpy 5.0.1): {reason} not found; {HINT}")
    raise RenderError(f"sim: blender: {python} cannot import bpy ({reason}); {HINT}")


def cycles_threads(threads: int | None = None) -> int:
    """Cycles' CPU threads: ``threads`` if given (``$UNDREAM_BLENDER_THREADS`` at the edge; a farm
    worker passes its share of the cores, ``drjit_threads``), else this process's Dr.Jit thread
    count; 0 (when Dr.Jit is not loaded) means all cores.
    """
    if threads is not None:
        return int(threads)
    drjit = sys.modules.get("drjit")
    return int(drjit.thread_count()) if drjit is not None else 0


@register_backend("blender")
class BlenderSimulator:
    """Renders frames of ``scene_dir`` with Cycles (CPU) through a lazily started render server.

    ``threads``: Cycles' CPU threads (default: :func:`cycles_threads`; 0: all
    cores); ``python``: Blender's interpreter (default :func:`blender_python`);
    ``env``: the server's environment (the edge's, :attr:`undream.settings.LocalSettings.child_env`;
    None: only what :func:`blender_env` sets).
    :attr:`server_threads` is the count the started server reports Cycles uses.
    """

    name = "blender"

    def __init__(self, scene_dir: Path, threads: int | None = None, python: str | Path | None = None,
                 env: Mapping[str, str] | None = None, **_shared: Any):
        self.scene_dir = Path(scene_dir).resolve()
        self.python = blender_python(python)
        self.env = env
        self.threads = cycles_threads(threads)
        self._proc: subprocess.Popen | None = None
        self._root: Path | None = None
        self._finalizer: weakref.finalize | None = None
        self._versions: dict[str, str] = {}
        self.server_threads: int | None = None  # Cycles' threads, as the server reports them once started
        check_blender(self.python)

    def _start(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        self._root = root = import_root()
        env = blender_env(root, self.env)
        cmd = [str(self.python), "-m", "undream.sim.blender_server", str(self.scene_dir),
               "--threads", str(self.threads)]
        with open(root / "server.log", "wb") as log:  # Blender's own output, for errors
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
                                          env=env, cwd=str(root))
        # Stops the server when this backend is garbage-collected or the process exits.
        self._finalizer = weakref.finalize(self, _shutdown, self._proc, root)
        header, _ = self._receive("starting the Cycles server")
        self._versions = {str(k): str(v) for k, v in header.get("versions", {}).items()}
        self.server_threads = int(header["threads"]) if "threads" in header else None
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

    def started(self) -> "BlenderSimulator":
        """Start the render server now (it starts on the first render otherwise); returns self."""
        self._start()
        return self

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
