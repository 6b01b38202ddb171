"""Scene directories in the blob store: packed once, content-addressed, unpacked once per machine.

A run records the SHA-256 of its scene directory packed as a tar file with a
fixed order and fixed metadata (``scenes/<sha256>.tar``), so the same scene
submitted twice is stored once and a worker on any machine gets exactly the
files the run was validated with. Each machine unpacks a scene once into its
cache folder (``<cache_dir>/scenes/<sha256>``), atomically: into a temporary
sibling that is renamed into place, so concurrent worker processes never see
half a scene.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

from undream.errors import StoreError
from undream.store import BlobStore, scene_key


def _tar_info(path: Path, arcname: str) -> tarfile.TarInfo:
    info = tarfile.TarInfo(arcname)
    info.mtime = 0
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    if path.is_dir():
        info.type, info.mode = tarfile.DIRTYPE, 0o755
    else:
        info.size, info.mode = path.stat().st_size, 0o644
    return info


def pack_scene(scene_dir: Path, out: Path) -> str:
    """Write ``scene_dir`` as a deterministic tar file ``out``; returns its SHA-256 (hex).

    Sorted paths, mtime 0, owner 0, modes 644/755: the same files give the same
    bytes. Symbolic links are followed (their targets are packed as files).
    """
    scene_dir = Path(scene_dir)
    if not (scene_dir / "sequence.json").is_file():
        raise StoreError(f"scene: {scene_dir} is not a scene directory (no sequence.json)")
    paths = sorted(p for p in scene_dir.rglob("*") if "__pycache__" not in p.parts)
    with tarfile.open(out, "w", format=tarfile.PAX_FORMAT) as tar:
        for p in paths:
            arcname = p.relative_to(scene_dir).as_posix()
            info = _tar_info(p, arcname)
            if info.isdir():
                tar.addfile(info)
            else:
                with open(p, "rb") as f:
                    tar.addfile(info, f)
    return _sha256(out)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def store_scene(blobs: BlobStore, scene_dir: Path) -> str:
    """Pack ``scene_dir`` into the blob store (once per content); returns its blob key."""
    with tempfile.TemporaryDirectory(prefix="undream-pack-") as tmp:
        tar = Path(tmp) / "scene.tar"
        key = scene_key(pack_scene(scene_dir, tar))
        if not blobs.exists(key):
            blobs.put_file(key, tar)
    return key


def unpack_scene(blobs: BlobStore, key: str, cache_dir: Path | str) -> Path:
    """The scene directory of blob ``key``, unpacked under ``cache_dir`` (once per machine)."""
    digest = Path(key).stem
    root = Path(cache_dir) / "scenes"
    dest = root / digest
    if (dest / "sequence.json").is_file():
        return dest
    src = blobs.get_file(key)
    if _sha256(src) != digest:
        raise StoreError(f"blob {key!r}: content does not match its SHA-256 (corrupt scene)")
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{digest[:12]}-", dir=root))
    try:
        with tarfile.open(src) as tar:
            tar.extractall(tmp, filter="data")
        try:
            os.rename(tmp, dest)
        except OSError:
            if not (dest / "sequence.json").is_file():  # not another process's finished copy
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return dest
