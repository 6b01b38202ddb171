"""Texture, gradient and attack-state blobs: files under one root, written atomically.

A key is a relative, ``/``-separated path of plain segments (letters, digits,
``_``, ``-``, ``.``; no segment starts with ``.``, so ``..`` and the writer's
temporary files can never be named). Arrays are ``.npy`` files, JSON
documents ``.json`` files. The layout of one run::

    runs/<run_id>/texture/000012.npy         texture k=12, H×W×3 float, sRGB 0–1
    runs/<run_id>/grad/000012/0003.npy       dL/dT of frame 3 at iteration 12
    runs/<run_id>/attack_state/000012.json   attack state after step 11 → 12 (scalars; arrays by key)
    runs/<run_id>/arrays/<sha256>.npy        an attack-state array (T0, visibility, ...), content-addressed
    runs/<run_id>/final/texture.npy          the 8-bit texture the adversarial evaluation renders
    runs/<run_id>/eval/<phase>/0003.npy      evaluation frame 3 (H×W×3 uint8 sRGB)
    scenes/<sha256>.tar                      a packed scene directory, content-addressed

The blob store is given as a URL like the database: a local folder
(``/srv/undream/blobs`` or ``file:///srv/undream/blobs``; a shared mount on a
cluster), see :func:`blob_root`.

Every write goes to a temporary file in the key's directory, is flushed to
disk, then renamed over the key (``os.replace``, :func:`undream.spec.io.atomic_write`): a reader
sees the old content or the new, never a partial file, even when the writer dies mid-write.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import tempfile
from urllib.parse import unquote, urlparse
from pathlib import Path
from typing import Any, Callable, IO

import numpy as np

from undream.errors import StoreError
from undream.spec.io import atomic_write

_SEGMENT = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]*$")
_TEMP_SUFFIX = ".tmp"


def texture_blob_key(run_id: str, k: int) -> str:
    """Key of texture ``k`` of a run (``k = 0`` is the starting texture)."""
    return f"runs/{run_id}/texture/{k:06d}.npy"


def grad_key(run_id: str, k: int, frame: int) -> str:
    """Key of frame ``frame``'s texture gradient at iteration ``k``."""
    return f"runs/{run_id}/grad/{k:06d}/{frame:04d}.npy"


def attack_state_key(run_id: str, k: int) -> str:
    """Key of the attack state that goes with texture ``k``."""
    return f"runs/{run_id}/attack_state/{k:06d}.json"


def array_key(run_id: str, digest: str) -> str:
    """Key of an attack-state array with content hash ``digest`` (see :func:`array_digest`)."""
    return f"runs/{run_id}/arrays/{digest}.npy"


def final_texture_key(run_id: str) -> str:
    """Key of the texture the adversarial evaluation renders (8-bit values as float)."""
    return f"runs/{run_id}/final/texture.npy"


def eval_image_key(run_id: str, phase: str, frame: int) -> str:
    """Key of evaluation frame ``frame`` of ``phase`` (``pre``: benign; ``adversarial``)."""
    return f"runs/{run_id}/eval/{phase}/{frame:04d}.npy"


def scene_key(digest: str) -> str:
    """Key of a packed scene directory whose tar file has SHA-256 ``digest``."""
    return f"scenes/{digest}.tar"


def array_digest(array: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (equal arrays, equal digests)."""
    arr = np.ascontiguousarray(array)
    h = hashlib.sha256(f"{arr.dtype.str}{arr.shape}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def blob_root(url: str | os.PathLike[str]) -> Path:
    """The folder of a blob-store URL: a path, or ``file:///path``; other schemes are a StoreError."""
    text = os.fspath(url)
    if not text:
        raise StoreError("blob URL: must be a folder path or file:///path, got ''")
    if "://" not in text:
        return Path(text).expanduser()
    parsed = urlparse(text)
    if parsed.scheme != "file" or parsed.netloc not in ("", "localhost"):
        raise StoreError(f"blob URL {text!r}: unsupported scheme {parsed.scheme!r}; give a folder "
                         "(a path or file:///path; a shared mount on a cluster)")
    return Path(unquote(parsed.path))


def run_prefix(run_id: str) -> str:
    """Prefix of every blob of a run."""
    return f"runs/{run_id}"


def check_key(key: Any, suffix: str | None = None) -> str:
    """``key`` if it is a valid relative blob key (ending in ``suffix``), else StoreError."""
    if not isinstance(key, str) or not key:
        raise StoreError(f"blob key {key!r}: must be a non-empty string")
    segments = key.split("/")
    bad = [s for s in segments if not _SEGMENT.match(s)]
    if bad:
        raise StoreError(f"blob key {key!r}: invalid segment {bad[0]!r}; a key is a relative "
                         "path of segments made of letters, digits, '_', '-' and '.', "
                         "not starting with '.' (no '..', no absolute paths)")
    if suffix is not None and not key.endswith(suffix):
        raise StoreError(f"blob key {key!r}: must end in {suffix!r}")
    return key


class BlobStore:
    """Arrays and JSON documents under ``root``, addressed by key."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        self.bytes_read = 0  # counters of array and file bytes moved by this process
        self.bytes_written = 0

    def path(self, key: str) -> Path:
        """The file that holds ``key`` (which need not exist)."""
        return self.root.joinpath(*check_key(key).split("/"))

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def put_array(self, key: str, array: np.ndarray) -> str:
        """Store ``array`` (any shape and numeric dtype) as ``.npy``; returns the key."""
        check_key(key, ".npy")
        arr = np.asarray(array)
        if arr.dtype.hasobject:
            raise StoreError(f"blob {key!r}: cannot store an object array; give a numeric array")
        self._write(key, lambda f: np.save(f, arr, allow_pickle=False))
        return key

    def get_array(self, key: str) -> np.ndarray:
        check_key(key, ".npy")
        try:
            data = self.path(key).read_bytes()
            self.bytes_read += len(data)
            return np.load(io.BytesIO(data), allow_pickle=False)
        except FileNotFoundError:
            raise StoreError(f"blob {key!r}: not found under {self.root}") from None
        except (OSError, ValueError) as exc:
            raise StoreError(f"blob {key!r}: unreadable .npy file: {exc}") from exc

    def put_json(self, key: str, data: Any) -> str:
        """Store ``data`` as strict JSON (NaN and infinities are an error); returns the key."""
        check_key(key, ".json")
        try:
            text = json.dumps(data, allow_nan=False, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise StoreError(f"blob {key!r}: not strict JSON-able: {exc}") from exc
        self._write(key, lambda f: f.write(text.encode("utf-8")))
        return key

    def get_json(self, key: str) -> Any:
        check_key(key, ".json")
        try:
            data = self.path(key).read_bytes()
            self.bytes_read += len(data)
            return json.loads(data.decode("utf-8"))
        except FileNotFoundError:
            raise StoreError(f"blob {key!r}: not found under {self.root}") from None
        except (OSError, ValueError) as exc:
            raise StoreError(f"blob {key!r}: unreadable JSON file: {exc}") from exc

    def put_file(self, key: str, src: Path | str) -> str:
        """Copy the file ``src`` to ``key`` (atomically, like every write); returns the key."""
        check_key(key)
        with open(src, "rb") as f_in:
            self._write(key, lambda f: shutil.copyfileobj(f_in, f, 1 << 20))
        return key

    def get_file(self, key: str) -> Path:
        """The local file holding ``key``; StoreError when there is none."""
        path = self.path(key)
        if not path.is_file():
            raise StoreError(f"blob {key!r}: not found under {self.root}")
        self.bytes_read += path.stat().st_size
        return path

    def check_writable(self) -> None:
        """Create and delete a probe file in the root; StoreError naming the folder and why when it
        cannot (a read-only mount, no permission, a full disk): a worker writes every texture and
        gradient there."""
        tmp: str | None = None
        try:
            fd, tmp = tempfile.mkstemp(prefix=".probe.", suffix=_TEMP_SUFFIX, dir=self.root)
            os.close(fd)
            os.unlink(tmp)
            tmp = None
        except OSError as exc:
            raise StoreError(f"blob folder {str(self.root)!r}: cannot write a file there "
                             f"({exc.strerror or exc}); the farm's processes write textures and "
                             "gradients there") from None
        finally:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> int:
        """Delete the blob ``prefix`` or every blob under the folder ``prefix``; returns the count."""
        target = self.path(prefix)
        if target.is_file():
            target.unlink()
            return 1
        if not target.is_dir():
            return 0
        count = sum(1 for p in target.rglob("*") if p.is_file())
        shutil.rmtree(target)
        return count

    def _write(self, key: str, write: Callable[[IO[bytes]], Any]) -> None:
        final = self.path(key)
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
            self.bytes_written += atomic_write(final, write, fsync=True, mode=0o600)
        except OSError as exc:
            raise StoreError(f"blob {key!r}: cannot write under {self.root}: {exc}") from exc
