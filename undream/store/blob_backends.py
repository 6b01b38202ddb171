"""Where blob bytes live: the small interface every blob backend implements, and the folder backend.

:class:`undream.store.blobs.BlobStore` is the interface the farm uses (arrays,
JSON, files; key rules; byte counters). It keeps the bytes in one
:class:`Backend`, which knows only keys (already checked) and bytes:

- :class:`FolderBackend`: files under a folder (one machine, or a mount every
  machine shares), written atomically (temporary file, fsync, rename), mode 0600;
- :class:`undream.store.blob_db.DatabaseBackend`: the ``blobs`` table of the run database;
- :class:`undream.store.blob_s3.S3Backend`: objects in an S3-compatible bucket.

A backend raises :class:`BlobMissing` for a key it does not hold and
:class:`undream.errors.StoreError` (one line, no secrets) when it cannot be
reached; the interface turns a missing key into a StoreError naming it.
"""
from __future__ import annotations

import datetime as dt
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from undream.errors import StoreError
from undream.spec.io import atomic_write

TEMP_SUFFIX = ".tmp"


class BlobMissing(KeyError):
    """The backend holds no blob under this key."""


@dataclass(frozen=True)
class BlobInfo:
    """One stored blob: its key, its size in bytes and when it was last written or touched (UTC)."""

    key: str
    size: int
    used: dt.datetime


class Backend(Protocol):
    """Bytes by key. Keys are checked by the caller (:func:`undream.store.blobs.check_key`)."""

    where: str  # where the blobs are, for messages (never a secret)

    def write(self, key: str, data: bytes, durable: bool = True) -> None:
        """Store ``data`` under ``key``, replacing any blob there; a reader sees old or new, whole.
        ``durable=False``: a blob that can be made again (a gradient) need not reach the disk
        before this returns (the folder skips its fsync); a process killed after it still leaves
        it whole, a machine that loses power may not."""

    def write_file(self, key: str, src: Path) -> int:
        """Store the file ``src`` under ``key`` like :meth:`write`; returns its size in bytes."""

    def read(self, key: str) -> bytes:
        """The bytes of ``key``; :class:`BlobMissing` when there is none."""

    def local_path(self, key: str) -> Path | None:
        """The local file that holds ``key`` if the backend keeps files (the folder), else None."""

    def exists(self, key: str) -> bool: ...

    def size(self, key: str) -> int:
        """The size of ``key`` in bytes; :class:`BlobMissing` when there is none."""

    def listing(self, prefix: str) -> list[BlobInfo]:
        """Every blob whose key is ``prefix`` or starts with ``prefix + '/'``."""

    def touch(self, key: str) -> None:
        """Mark ``key`` as used now (its ``BlobInfo.used``); nothing when it is gone."""

    def delete_prefix(self, prefix: str) -> int:
        """Delete the blob ``prefix`` and every blob under ``prefix + '/'``; returns how many."""

    def delete(self, keys: list[str]) -> None:
        """Delete the blobs ``keys`` (those still there)."""

    def check_writable(self) -> None:
        """StoreError naming the backend and why unless a blob can be written there now."""

    def close(self) -> None: ...


def _mtime(path: Path) -> dt.datetime:
    return dt.datetime.fromtimestamp(path.stat().st_mtime, dt.timezone.utc)


class FolderBackend:
    """Blobs as files under ``root``: ``runs/r/texture/000001.npy`` is ``root/runs/r/texture/000001.npy``."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        self.where = f"blob folder {str(self.root)!r}"

    def path(self, key: str) -> Path:
        return self.root.joinpath(*key.split("/"))

    def write(self, key: str, data: bytes, durable: bool = True) -> None:
        self._write(key, lambda f: f.write(data), durable)

    def write_file(self, key: str, src: Path) -> int:
        with open(src, "rb") as f_in:
            return self._write(key, lambda f: shutil.copyfileobj(f_in, f, 1 << 20))

    def _write(self, key: str, write: object, durable: bool = True) -> int:
        final = self.path(key)
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
            return atomic_write(final, write, fsync=durable, mode=0o600)  # type: ignore[arg-type]
        except OSError as exc:
            raise StoreError(f"blob {key!r}: cannot write under {self.root}: {exc}") from exc

    def read(self, key: str) -> bytes:
        try:
            return self.path(key).read_bytes()
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise BlobMissing(key) from None
        except OSError as exc:
            raise StoreError(f"blob {key!r}: cannot read under {self.root}: {exc}") from exc

    def local_path(self, key: str) -> Path | None:
        return self.path(key)

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def size(self, key: str) -> int:
        path = self.path(key)
        if not path.is_file():
            raise BlobMissing(key)
        return path.stat().st_size

    def listing(self, prefix: str) -> list[BlobInfo]:
        target = self.path(prefix)
        if target.is_file():
            return [BlobInfo(prefix, target.stat().st_size, _mtime(target))]
        out = []
        for path in sorted(target.rglob("*")) if target.is_dir() else []:
            if path.is_file() and not path.name.startswith("."):  # a writer's temporary file is no blob
                try:
                    out.append(BlobInfo(path.relative_to(self.root).as_posix(), path.stat().st_size,
                                        _mtime(path)))
                except FileNotFoundError:  # deleted while listed
                    continue
        return out

    def touch(self, key: str) -> None:
        try:
            os.utime(self.path(key))
        except OSError:  # gone, or a read-only mount: the cache then forgets use, not data
            pass

    def delete_prefix(self, prefix: str) -> int:
        target = self.path(prefix)
        if target.is_file():
            target.unlink()
            return 1
        if not target.is_dir():
            return 0
        count = sum(1 for p in target.rglob("*") if p.is_file())
        shutil.rmtree(target, ignore_errors=True)
        return count

    def delete(self, keys: list[str]) -> None:
        for key in keys:
            self.path(key).unlink(missing_ok=True)

    def check_writable(self) -> None:
        tmp: str | None = None
        try:
            fd, tmp = tempfile.mkstemp(prefix=".probe.", suffix=TEMP_SUFFIX, dir=self.root)
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

    def close(self) -> None:
        pass
