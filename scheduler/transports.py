"""Captured transports shared by every worker through the blob store, per scene.

A frame's transport depends on its scene, its capture seed (run seed, frame,
refresh epoch) and spp only, so the first process to capture it leaves it
under ``transports/<scene digest>/`` and the others read it instead of
capturing again (measured: a capture costs about 2 frame jobs at 64 px, a
read of its ``.npz`` a few milliseconds). The linearity verdict of each frame
is shared the same way. Everything under ``transports/`` is a cache: deleting
it costs captures, never results.
"""
from __future__ import annotations

import os
import tempfile
from typing import TYPE_CHECKING

from undream.errors import StoreError

if TYPE_CHECKING:
    from undream.render.transport import Transport
    from undream.store.blobs import BlobStore


def scene_digest(scene_ref: str) -> str:
    """The digest part of a scene blob key (``scenes/<digest>.tar``)."""
    return scene_ref.rsplit("/", 1)[-1].removesuffix(".tar")


class BlobTransportShelf:
    """:class:`undream.engine.gradient.TransportShelf` over a :class:`BlobStore`, for one scene."""

    def __init__(self, blobs: "BlobStore", scene_ref: str) -> None:
        self.blobs = blobs
        self.prefix = f"transports/{scene_digest(scene_ref)}"
        self.hits = self.misses = 0

    def get(self, key: str) -> "Transport | None":
        from undream.render.transport import Transport

        blob = f"{self.prefix}/{key}.npz"
        if not self.blobs.exists(blob):
            self.misses += 1
            return None
        try:
            t = Transport.load(self.blobs.get_file(blob))
        except (StoreError, OSError, ValueError, KeyError):  # half-deleted cache: capture again
            self.misses += 1
            return None
        self.hits += 1
        return t

    def put(self, key: str, transport: "Transport") -> None:
        fd, tmp = tempfile.mkstemp(suffix=".npz")
        os.close(fd)
        try:
            transport.save(tmp)
            self.blobs.put_file(f"{self.prefix}/{key}.npz", tmp)
        finally:
            os.unlink(tmp)

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
