"""Texture, gradient and attack-state blobs: bytes by key, in a folder, the run database or S3.

A key is a relative, ``/``-separated path of plain segments (letters, digits,
``_``, ``-``, ``.``; no segment starts with ``.``, so ``..`` and the writer's
temporary files can never be named). Arrays are ``.npy`` files, JSON
documents ``.json`` files. The layout of one run::

    runs/<run_id>/texture/000012.npy         texture k=12, H×W×3 float, sRGB 0–1
    runs/<run_id>/grad/000012/0003.npy       dL/dT of frame 3 at iteration 12 (deleted once reduced)
    runs/<run_id>/attack_state/000012.json   attack state after step 11 → 12 (scalars; arrays by key)
    runs/<run_id>/arrays/<sha256>.npy        an attack-state array (T0, visibility, ...), content-addressed
    runs/<run_id>/seen.npy                   H×W bool: texels iteration 0's frames see (the dashboard's mask)
    runs/<run_id>/final/texture.npy          the 8-bit texture the adversarial evaluation renders
    runs/<run_id>/eval/<phase>/0003.npy      evaluation frame 3 (H×W×3 uint8 sRGB)
    scenes/<sha256>.tar                      a packed scene directory, content-addressed
    transports/<scene sha256>/...            captured transports: a cache, capped (scheduler.transports)

The blob store is given as a URL (:func:`parse_blob_url`): a folder
(``/srv/undream/blobs`` or ``file:///srv/undream/blobs``; a shared mount on a
cluster), ``database`` (the run database's ``blobs`` table), or
``s3://bucket/prefix`` (S3-compatible object storage). :class:`BlobStore` is
the one interface; the bytes live in a backend (:mod:`undream.store.blob_backends`).

The interface's promises, whatever the backend: keys are checked
(:func:`check_key`); a write is whole or absent (a reader sees the old content
or the new, never a part, even when the writer dies mid-write) and writing a
key twice is harmless (idempotent); content-addressed keys (arrays, scenes)
are written once per content; a missing key is a one-line StoreError naming it.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Iterator
from urllib.parse import unquote, urlparse

import numpy as np

from undream.errors import StoreError
from undream.spec.io import atomic_write
from undream.store.blob_backends import Backend, BlobInfo, BlobMissing, FolderBackend

if TYPE_CHECKING:
    from undream.settings import Settings

_SEGMENT = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]*$")
DATABASE = "database"  # the blob URL that keeps blobs in the run database


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


def seen_key(run_id: str) -> str:
    """Key of the run's seen-texel mask (H×W bool), kept when iteration 0's gradients are deleted."""
    return f"runs/{run_id}/seen.npy"


def grad_prefix(run_id: str, k: int) -> str:
    """Prefix of every frame gradient of iteration ``k`` (or of every iteration, ``k`` None)."""
    return f"runs/{run_id}/grad" if k is None else f"runs/{run_id}/grad/{k:06d}"


def event_prefix(run_id: str) -> str:
    """Prefix of the run's event lines (:mod:`undream.store.events`)."""
    return f"runs/{run_id}/events"


def scene_key(digest: str) -> str:
    """Key of a packed scene directory whose tar file has SHA-256 ``digest``."""
    return f"scenes/{digest}.tar"


def array_digest(array: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (equal arrays, equal digests)."""
    arr = np.ascontiguousarray(array)
    h = hashlib.sha256(f"{arr.dtype.str}{arr.shape}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()


_VALID_URL = ("give a folder (a path or file:///path; a shared mount on a cluster), 'database' "
              "(the run database's blobs table) or s3://bucket/prefix")


@dataclass(frozen=True)
class BlobOptions:
    """How this process reaches its blobs, beyond the URL (from the settings, at the edge).

    ``local_dir``: a folder on this machine for copies of blobs that are not
    files (:meth:`BlobStore.get_file`) and for the outputs of runs submitted
    without ``--out`` (None: a temporary folder). ``s3_*``: the S3 endpoint
    (None: AWS), region and keys (None: boto3's own chain). Keys never show in a repr.
    """

    local_dir: str | None = None
    s3_endpoint_url: str | None = None
    s3_region: str | None = None
    s3_access_key_id: str | None = field(default=None, repr=False)
    s3_secret_access_key: str | None = field(default=None, repr=False)

    @classmethod
    def of(cls, settings: "Settings") -> "BlobOptions":
        """The options of a farm's settings (local copies under its ``cache_dir``)."""
        return cls(local_dir=settings.cache_dir, s3_endpoint_url=settings.s3_endpoint_url,
                   s3_region=settings.s3_region, s3_access_key_id=settings.s3_access_key_id,
                   s3_secret_access_key=settings.s3_secret_access_key)


@dataclass(frozen=True)
class BlobURL:
    """A parsed blob URL: ``kind`` folder (``root``), database, or s3 (``bucket``, ``prefix``)."""

    kind: str
    root: Path | None = None
    bucket: str = ""
    prefix: str = ""


def parse_blob_url(url: str | os.PathLike[str]) -> BlobURL:
    """The backend a blob URL names; StoreError naming the URL and what is valid otherwise."""
    text = os.fspath(url)
    if not text:
        raise StoreError(f"blob URL '': {_VALID_URL}")
    if text == DATABASE:
        return BlobURL("database")
    if "://" not in text:
        return BlobURL("folder", Path(text).expanduser())
    parsed = urlparse(text)
    if parsed.scheme == "file" and parsed.netloc in ("", "localhost"):
        return BlobURL("folder", Path(unquote(parsed.path)))
    if parsed.scheme == "s3":
        bucket, prefix = parsed.hostname or "", parsed.path.strip("/")
        if parsed.username or parsed.password or parsed.query or parsed.port:
            raise StoreError(f"blob URL 's3://{bucket}/{prefix}': give only s3://bucket/prefix; credentials "
                             "and the endpoint are the settings s3_access_key_id, s3_secret_access_key and "
                             "s3_endpoint_url")
        if not re.fullmatch(r"[a-z0-9][a-z0-9.-]{1,61}[a-z0-9]", bucket):
            raise StoreError(f"blob URL {text!r}: {bucket!r} is not a bucket name (3 to 63 lowercase "
                             "letters, digits, '.' and '-')")
        if prefix:
            check_key(prefix)
        return BlobURL("s3", bucket=bucket, prefix=prefix)
    shown = f"{parsed.scheme}://{parsed.hostname or ''}{parsed.path}"
    raise StoreError(f"blob URL {shown!r}: unsupported scheme {parsed.scheme!r}; {_VALID_URL}")


def blob_root(url: str | os.PathLike[str]) -> Path:
    """The folder of a folder blob URL (a path, or ``file:///path``); StoreError for another backend."""
    parsed = parse_blob_url(url)
    if parsed.root is None:
        raise StoreError(f"blob URL {os.fspath(url)!r}: not a folder; {_VALID_URL}")
    return parsed.root


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
    """Arrays, JSON documents and files by key, in one backend (a folder root, or a :class:`Backend`).

    ``local_dir``: a folder on this machine for the copies :meth:`get_file`
    makes of blobs a non-folder backend holds (``<local_dir>/blobs/<key>``);
    None: a temporary folder of this process, removed by :meth:`close`.
    """

    def __init__(self, backend: "Backend | Path | str", local_dir: Path | str | None = None) -> None:
        self.backend: Backend = FolderBackend(backend) if isinstance(backend, (str, os.PathLike)) else backend
        self.root: Path | None = self.backend.root if isinstance(self.backend, FolderBackend) else None
        self._local_dir = None if local_dir is None else Path(local_dir)
        self._temp_dir: str | None = None
        self.bytes_read = 0  # counters of array and file bytes moved by this process
        self.bytes_written = 0

    @property
    def where(self) -> str:
        """Where the blobs are, for messages (no secrets)."""
        return self.backend.where

    def __repr__(self) -> str:
        return f"BlobStore({self.where})"

    @property
    def local_dir(self) -> Path:
        """A folder on this machine: the blob folder itself, else ``local_dir`` (or a temporary one)."""
        if self.root is not None:
            return self.root
        if self._local_dir is not None:
            return self._local_dir
        if self._temp_dir is None:
            self._temp_dir = tempfile.mkdtemp(prefix="undream-blobs-")
        return Path(self._temp_dir)

    def close(self) -> None:
        """Close the backend's connections and remove this process's temporary copies."""
        self.backend.close()
        if self._temp_dir is not None:
            shutil.rmtree(self._temp_dir, ignore_errors=True)
            self._temp_dir = None

    @contextmanager
    def joined(self, conn: Any) -> Iterator[None]:
        """Blob reads and writes of this thread inside the database transaction of ``conn``, for a
        backend that lives in the database (a no-op for the others)."""
        bind = getattr(self.backend, "bind", None)
        if bind is None:
            yield
            return
        with bind(conn):
            yield

    def path(self, key: str) -> Path:
        """The file that holds ``key`` (which need not exist); folder backends only."""
        check_key(key)
        if not isinstance(self.backend, FolderBackend):
            raise StoreError(f"blob {key!r}: the blobs are in the {self.where}, not files; "
                             "read it with get_file")
        return self.backend.path(key)

    def exists(self, key: str) -> bool:
        return self.backend.exists(check_key(key))

    def size(self, key: str) -> int:
        """The size of blob ``key`` in bytes; StoreError naming the key when there is none."""
        try:
            return self.backend.size(check_key(key))
        except BlobMissing:
            raise self._missing(key) from None

    def listing(self, prefix: str) -> list[BlobInfo]:
        """Every blob ``prefix`` or under ``prefix/``: key, size and last use."""
        return self.backend.listing(check_key(prefix))

    def usage(self, prefix: str) -> tuple[int, int]:
        """(blobs, bytes) stored under ``prefix``."""
        items = self.listing(prefix)
        return len(items), sum(i.size for i in items)

    def touch(self, key: str) -> None:
        """Mark ``key`` used now (the transport cache evicts the least recently used)."""
        self.backend.touch(check_key(key))

    def put_array(self, key: str, array: np.ndarray, durable: bool = True) -> str:
        """Store ``array`` (any shape and numeric dtype) as ``.npy``; returns the key.
        ``durable=False``: an array that can be computed again (see :meth:`Backend.write`)."""
        check_key(key, ".npy")
        arr = np.asarray(array)
        if arr.dtype.hasobject:
            raise StoreError(f"blob {key!r}: cannot store an object array; give a numeric array")
        buf = io.BytesIO()
        np.save(buf, arr, allow_pickle=False)
        self._write(key, buf.getvalue(), durable)
        return key

    def get_array(self, key: str) -> np.ndarray:
        data = self.get_bytes(check_key(key, ".npy"))
        try:
            return np.load(io.BytesIO(data), allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise StoreError(f"blob {key!r}: unreadable .npy file: {exc}") from exc

    def put_json(self, key: str, data: Any) -> str:
        """Store ``data`` as strict JSON (NaN and infinities are an error); returns the key."""
        check_key(key, ".json")
        try:
            text = json.dumps(data, allow_nan=False, sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise StoreError(f"blob {key!r}: not strict JSON-able: {exc}") from exc
        self._write(key, text.encode("utf-8"))
        return key

    def get_json(self, key: str) -> Any:
        data = self.get_bytes(check_key(key, ".json"))
        try:
            return json.loads(data.decode("utf-8"))
        except ValueError as exc:
            raise StoreError(f"blob {key!r}: unreadable JSON file: {exc}") from exc

    def get_bytes(self, key: str) -> bytes:
        """The bytes of blob ``key``; StoreError naming the key when there is none."""
        try:
            data = self.backend.read(check_key(key))
        except BlobMissing:
            raise self._missing(key) from None
        self.bytes_read += len(data)
        return data

    @contextmanager
    def open(self, key: str) -> Iterator[IO[bytes]]:
        """Blob ``key`` as a binary file to read (the file itself in a folder, else its bytes)."""
        path = self.backend.local_path(check_key(key))
        if path is None:
            yield io.BytesIO(self.get_bytes(key))
            return
        try:
            f = open(path, "rb")
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            raise self._missing(key) from None
        with f:
            self.bytes_read += os.fstat(f.fileno()).st_size
            yield f

    def put_bytes(self, key: str, data: bytes, durable: bool = True) -> str:
        """Store ``data`` under ``key`` (atomically); returns the key. ``durable=False``: bytes that
        can be made again (a cache's) need not reach the disk first (see :meth:`Backend.write`)."""
        check_key(key)
        self._write(key, bytes(data), durable)
        return key

    def put_file(self, key: str, src: Path | str) -> str:
        """Copy the file ``src`` to ``key`` (atomically, like every write); returns the key."""
        check_key(key)
        self.bytes_written += self.backend.write_file(key, Path(src))
        return key

    def get_file(self, key: str) -> Path:
        """A local file holding ``key``: the blob's own file in a folder, else a fresh copy under
        ``<local_dir>/blobs/`` (written atomically); StoreError naming the key when there is none."""
        path = self.backend.local_path(check_key(key))
        if path is not None:
            if not path.is_file():
                raise self._missing(key)
            self.bytes_read += path.stat().st_size
            return path
        data = self.get_bytes(key)
        copy = self.local_dir.joinpath("blobs", *key.split("/"))
        try:
            copy.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(copy, data, mode=0o600)
        except OSError as exc:
            raise StoreError(f"blob {key!r}: cannot copy it to {copy.parent}: {exc}") from exc
        return copy

    def check_writable(self) -> None:
        """StoreError naming the backend and why unless a blob can be written there (a read-only
        mount, no permission, a full disk, a bucket that refuses): a worker writes every texture
        and gradient there."""
        self.backend.check_writable()

    def delete_prefix(self, prefix: str) -> int:
        """Delete the blob ``prefix`` or every blob under ``prefix/``; returns the count."""
        return self.backend.delete_prefix(check_key(prefix))

    def delete(self, keys: list[str]) -> None:
        """Delete the blobs ``keys`` (missing ones are no error)."""
        self.backend.delete([check_key(k) for k in keys])

    def _missing(self, key: str) -> StoreError:
        return StoreError(f"blob {key!r}: not found in the {self.where}")

    def _write(self, key: str, data: bytes, durable: bool = True) -> None:
        self.backend.write(key, data, durable)
        self.bytes_written += len(data)
