"""The ``unreal`` simulator: frames rendered by Unreal Engine's Movie Render Queue, through a spool folder.

Unreal runs elsewhere (an editor on a Windows or Linux workstation); a
worker script inside that editor (``deploy/unreal/render_texture.py --spool
DIR``) serves the frame jobs. The two sides share one folder, the *spool*
(the backend's ``spool`` option; ``$UNDREAM_UNREAL_SPOOL`` at the edge), and talk
through files only, so any shared file system works (SMB, NFS, a synced
folder). The protocol, version 1 (``docs/unreal.md``)::

    SPOOL/worker.json            the editor worker, when it starts: {"format": "undream-unreal-worker",
                                 "version": 1, "engine": "5.4.4-...", "project": ..., "sequence": ...}
    SPOOL/requests/ID.png        the texture: sRGB, 8 bits per channel (written first)
    SPOOL/requests/ID.json       the request, written last (atomically: a rename):
                                 {"format": "undream-unreal-request", "version": 1, "id": ID,
                                  "sequence": NAME, "frame": N, "resolution": [W, H], "spp": S,
                                  "seed": SEED, "texture": "ID.png"}
    SPOOL/responses/ID.exr|png   the rendered frame (EXR: linear radiance; PNG: sRGB)
    SPOOL/responses/ID.json      written last: {"format": "undream-unreal-response", "version": 1,
                                 "id": ID, "image": "ID.exr", "space": "linear" | "srgb",
                                 "seconds": t, "engine": "5.4.4-..."}  or  {"id": ID, "error": "one line"}

The editor claims a request by renaming ``ID.json`` to ``ID.json.taken``;
this backend waits for ``responses/ID.json`` (``timeout_s``, default
600 s; ``$UNDREAM_UNREAL_TIMEOUT`` at the edge), reads the frame, and removes the
request and response files. ``frame`` is the frame's index in the scene's
``sequence.json`` (for an Unreal export, Unreal's own frame number). Every
failure is one :class:`RenderError` line: no answer in time, an error the
editor reported, a malformed response.
"""
from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from undream.color import srgb_to_linear, to_uint8
from undream.errors import RenderError
from undream.settings import UNREAL_SPOOL_ENV, UNREAL_TIMEOUT_ENV
from undream.sim import register_backend
from undream.spec import load_sequence
from undream.spec.io import atomic_write
from undream.variant import mitsuba

SPOOL_ENV, TIMEOUT_ENV = UNREAL_SPOOL_ENV, UNREAL_TIMEOUT_ENV  # named in messages; read at the edge
DEFAULT_TIMEOUT_S = 600.0
REQUEST_FORMAT, RESPONSE_FORMAT, WORKER_FORMAT = "undream-unreal-request", "undream-unreal-response", \
    "undream-unreal-worker"
VERSION = 1
IMAGE_SUFFIXES = {".exr": "linear", ".png": "srgb"}


def spool_folder(spool: str | Path | None = None) -> Path:
    """The spool folder ``spool`` (``$UNDREAM_UNREAL_SPOOL`` at the edge); a one-line RenderError
    when it is not given or not a folder."""
    value = spool
    if not value:
        raise RenderError(f"sim: unreal needs a spool folder shared with the editor's worker "
                          f"(deploy/unreal/render_texture.py --spool DIR): set {SPOOL_ENV} (docs/unreal.md)")
    path = Path(value)
    if not path.is_dir():
        raise RenderError(f"sim: unreal: spool folder {path} not found ({SPOOL_ENV}); create it and start "
                          "deploy/unreal/render_texture.py --spool on it beside the editor")
    if not os.access(path, os.W_OK | os.X_OK):
        raise RenderError(f"sim: unreal: no permission to write in the spool folder {path}")
    return path


def check_unreal(spool: str | Path | None = None) -> None:
    """Raise a one-line RenderError unless the spool folder is set and writable (before anything is written)."""
    spool_folder(spool)


@register_backend("unreal")
class UnrealSimulator:
    """Hands frame renders of ``scene_dir`` to an Unreal editor worker through the spool folder.

    ``spool``: the shared folder (the edge passes ``$UNDREAM_UNREAL_SPOOL``);
    ``timeout_s``: how long to wait for one frame (default 600 s; the edge
    passes ``$UNDREAM_UNREAL_TIMEOUT``); ``poll_s``: how often to look.
    """

    name = "unreal"

    def __init__(self, scene_dir: Path, spool: str | Path | None = None, timeout_s: float | None = None,
                 poll_s: float = 0.05, **_shared: Any):
        self.spool = spool_folder(spool)
        given: Any = timeout_s if timeout_s is not None else DEFAULT_TIMEOUT_S
        try:
            timeout = float(given)
        except (TypeError, ValueError):
            timeout = float("nan")
        if not timeout > 0:
            raise RenderError(f"sim: unreal: the timeout ({TIMEOUT_ENV} or timeout_s) must be a number of "
                              f"seconds > 0, got {given!r}")
        self.timeout_s, self.poll_s = float(timeout), float(poll_s)
        self.seq = load_sequence(Path(scene_dir) / "sequence.json")
        self.frames = {f.index: f for f in self.seq.frames}
        self.requests, self.responses = self.spool / "requests", self.spool / "responses"
        for folder in (self.requests, self.responses):
            folder.mkdir(exist_ok=True)
        self._engine: str | None = None

    def render(self, index: int, texture_srgb: np.ndarray, spp: int, seed: int,
               conditions: Any = None) -> np.ndarray:
        """Frame ``index`` with ``texture_srgb`` (H×W×3 sRGB in [0, 1], sent as 8-bit PNG): H×W×3 linear radiance."""
        if conditions is not None:
            raise RenderError("sim: unreal cannot move the camera and light per render (eot); use sim: mitsuba")
        if index not in self.frames:
            raise RenderError(f"sim: unreal: frame {index} is not in the scene's sequence")
        tex = np.asarray(texture_srgb, dtype=np.float32)
        if tex.ndim != 3 or tex.shape[2] != 3 or not np.isfinite(tex).all():
            raise RenderError(f"texture must be a finite H×W×3 array, got shape {tex.shape}")
        rid = f"{self.seq.name}-{index:04d}-{uuid.uuid4().hex[:12]}"
        request = self._send(rid, index, tex, spp, seed)
        try:
            header = self._wait(rid, index, request)
            return self._read_frame(rid, index, header)
        finally:
            self._clean(rid)

    def _send(self, rid: str, index: int, tex: np.ndarray, spp: int, seed: int) -> Path:
        Image.fromarray(to_uint8(tex)).save(self.requests / f"{rid}.png")
        w, h = self.frames[index].camera.resolution
        request = self.requests / f"{rid}.json"
        atomic_write(request, json.dumps({
            "format": REQUEST_FORMAT, "version": VERSION, "id": rid, "sequence": self.seq.name, "frame": index,
            "resolution": [w, h], "spp": int(spp), "seed": int(seed), "texture": f"{rid}.png"}))
        return request

    def _wait(self, rid: str, index: int, request: Path) -> dict[str, Any]:
        answer = self.responses / f"{rid}.json"
        deadline = time.monotonic() + self.timeout_s
        while not answer.is_file():
            if time.monotonic() > deadline:
                taken = request.with_name(request.name + ".taken").exists()
                state = "taken by a worker but not answered" if taken else "not taken by any worker"
                raise RenderError(f"sim: unreal: frame {index}: no answer from the editor in {self.timeout_s:g} s "
                                  f"(request {request}: {state}); is deploy/unreal/render_texture.py "
                                  f"serving {self.spool}?")
            time.sleep(self.poll_s)
        try:
            header = json.loads(answer.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise self._malformed(index, answer, f"not JSON ({err})") from None
        if not isinstance(header, dict) or header.get("id") != rid:
            raise self._malformed(index, answer, f"must be a JSON object with \"id\": {rid!r}")
        if "error" in header:
            raise RenderError(" ".join(f"sim: unreal: frame {index}: the editor says: {header['error']}".split()))
        return header

    def _malformed(self, index: int, path: Path, why: str) -> RenderError:
        return RenderError(" ".join(f"sim: unreal: frame {index}: malformed response {path}: {why}".split()))

    def _read_frame(self, rid: str, index: int, header: dict[str, Any]) -> np.ndarray:
        answer = self.responses / f"{rid}.json"
        if header.get("format") != RESPONSE_FORMAT or header.get("version") != VERSION:
            raise self._malformed(index, answer, f"format must be {RESPONSE_FORMAT!r} version {VERSION}")
        image = header.get("image")
        if not isinstance(image, str) or Path(image).name != image or Path(image).suffix.lower() not in IMAGE_SUFFIXES:
            raise self._malformed(index, answer, f"\"image\" must name an .exr or .png file in {self.responses}, "
                                                 f"got {image!r}")
        space = IMAGE_SUFFIXES[Path(image).suffix.lower()]
        if header.get("space", space) != space:
            raise self._malformed(index, answer, f"\"space\" of a {Path(image).suffix} frame must be {space!r}")
        path = self.responses / image
        try:
            pixels = _read_linear(path, space)
        except (OSError, ValueError, RuntimeError) as err:
            raise self._malformed(index, answer, f"cannot read {path} ({' '.join(str(err).split())[:200]})") from None
        w, h = self.frames[index].camera.resolution
        if pixels.shape != (h, w, 3):
            raise self._malformed(index, answer, f"{image} is {pixels.shape[1]}×{pixels.shape[0]} px, "
                                                 f"the frame's camera renders {w}×{h}")
        if not np.isfinite(pixels).all():
            raise self._malformed(index, answer, f"{image} holds NaN or infinite values")
        if isinstance(header.get("engine"), str):
            self._engine = header["engine"]
        return pixels

    def _clean(self, rid: str) -> None:
        for folder in (self.requests, self.responses):
            for path in folder.glob(f"{rid}.*"):
                path.unlink(missing_ok=True)

    def versions(self) -> dict[str, str]:
        """The engine version the editor worker reported (``worker.json``, or the last response)."""
        out = {"unreal_spool": str(self.spool)}
        try:
            info = json.loads((self.spool / "worker.json").read_text())
        except (OSError, ValueError):
            info = {}
        if not isinstance(info, dict) or info.get("format") != WORKER_FORMAT:
            info = {}
        engine = self._engine or info.get("engine")
        out["unreal"] = str(engine) if engine else "unknown (no worker.json yet)"
        return out


def _read_linear(path: Path, space: str) -> np.ndarray:
    """H×W×3 float32 linear radiance from an EXR (as stored) or a PNG (sRGB 8 or 16 bit, decoded)."""
    if space == "linear":
        mi = mitsuba()
        bitmap = mi.Bitmap(str(path))
        arr = np.array(bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False),
                       dtype=np.float32)
        return arr.reshape(arr.shape[0], arr.shape[1], -1)[..., :3]
    with Image.open(path) as img:
        if img.mode in ("I;16", "I;16B", "I"):
            raise ValueError("a one-channel 16-bit PNG is not an RGB frame")
        rgb = np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0
    return srgb_to_linear(rgb).astype(np.float32)
