"""Captured transports shared by every worker through the blob store, per scene.

A frame's transport depends on its scene, its capture seed (run seed, frame,
refresh epoch) and spp only, so the first process to capture it leaves it
under ``transports/<scene digest>/`` and the others read it instead of
capturing again (measured: a capture costs about 2 frame jobs at 64 px, a
read of its ``.npz`` a few milliseconds). The linearity verdict of each frame
is shared the same way. Everything under ``transports/`` is a cache: deleting
it costs captures, never results, and it is written without waiting for the disk
(a blob a power cut tore is a miss: captured again).

The cache is capped (the setting ``transport_cache_mb``, default
:data:`DEFAULT_CACHE_MB`): after each capture it writes, a process lists
``transports/`` with sizes and last-use times (:meth:`undream.store.BlobStore.listing`,
on every backend) and deletes the least recently used blobs until the rest
fit. A hit marks its blob used (at most once a minute per process:
a file's mtime, a row's ``used``, an object copied onto itself). A transport
deleted while another process reads it is a miss there: it captures again.
"""
from __future__ import annotations

import io
import time
import zipfile
from typing import TYPE_CHECKING

from undream.errors import StoreError

if TYPE_CHECKING:
    from undream.render.transport import Transport
    from undream.store.blobs import BlobStore


PREFIX = "transports"
DEFAULT_CACHE_MB = 512
TOUCH_EVERY_S = 60.0  # a hit renews its blob's last use at most this often per process


def prune_transports(blobs: "BlobStore", cap_bytes: int) -> int:
    """Delete the least recently used blobs under ``transports/`` until the rest total at most
    ``cap_bytes``; returns how many were deleted."""
    items = blobs.listing(PREFIX)
    total = sum(i.size for i in items)
    doomed = []
    for item in sorted(items, key=lambda i: (i.used, i.key)):
        if total <= cap_bytes:
            break
        doomed.append(item.key)
        total -= item.size
    blobs.delete(doomed)
    return len(doomed)


def scene_digest(scene_ref: str) -> str:
    """The digest part of a scene blob key (``scenes/<digest>.tar``)."""
    return scene_ref.rsplit("/", 1)[-1].removesuffix(".tar")


class BlobTransportShelf:
    """:class:`undream.engine.gradient.TransportShelf` over a :class:`BlobStore`, for one scene;
    ``cap_bytes``: the size of the whole transport cache (every scene's), see the module docstring."""

    def __init__(self, blobs: "BlobStore", scene_ref: str, cap_bytes: int = DEFAULT_CACHE_MB << 20) -> None:
        self.blobs = blobs
        self.prefix = f"{PREFIX}/{scene_digest(scene_ref)}"
        self.cap_bytes = cap_bytes
        self.hits = self.misses = self.evicted = 0
        self._touched: dict[str, float] = {}  # blob → when this process last marked it used

    def get(self, key: str) -> "Transport | None":
        from undream.render.transport import Transport

        blob = f"{self.prefix}/{key}.npz"
        try:
            with self.blobs.open(blob) as f:
                t = Transport.load(f)
        except (StoreError, OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            self.misses += 1  # not there, or evicted while read: capture again
            return None
        self.hits += 1
        now = time.monotonic()
        if now - self._touched.get(blob, -TOUCH_EVERY_S) >= TOUCH_EVERY_S:
            self._touched[blob] = now
            self.blobs.touch(blob)
        return t

    def put(self, key: str, transport: "Transport") -> None:
        buf = io.BytesIO()
        transport.save(buf)
        # a cache: written without waiting for the disk; one a power cut tore is a miss (captured again)
        self.blobs.put_bytes(f"{self.prefix}/{key}.npz", buf.getbuffer(), durable=False)
        self._touched[f"{self.prefix}/{key}.npz"] = time.monotonic()
        self.evicted += prune_transports(self.blobs, self.cap_bytes)

    def get_verdict(self, index: int) -> tuple[bool, str | None]:
        blob = f"{self.prefix}/linear-{index}.json"
        if not self.blobs.exists(blob):
            return False, None
        try:
            return True, self.blobs.get_json(blob)["reason"]
        except (StoreError, KeyError, TypeError):
            return False, None

    def put_verdict(self, index: int, reason: str | None) -> None:
        self.blobs.put_json(f"{self.prefix}/linear-{index}.json", {"reason": reason})
