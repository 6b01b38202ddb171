"""Realistic objects fetched and converted at setup, named in scene files as ``asset:NAME``.

``deploy/setup.sh`` runs ``deploy/fetch_assets.py``, which fetches Debian
packages at pinned versions (``deploy/assets.lock.json``) and converts them
into ``CACHE/assets/NAME/`` (``CACHE``: ``$XDG_CACHE_HOME/undream``, default
``~/.cache/undream``): ``mesh.ply`` (canonical: Y up, metres, UV-mapped),
``texture.png`` for an asset meant to be attacked (its starting texture, sRGB)
and ``asset.json`` (source package, licence, scale; an actor's baked
``color``). A scene file names them where it names a mesh or a starting
texture::

    object:
      asset: {name: car, mesh: asset:p406, texture: {resolution: [512, 512], init: asset:p406}}
    actors:
      - asset: {name: wheels, mesh: asset:p406_wheels, color: [0.03, 0.03, 0.03]}

and :func:`resolve` turns the name into the cached file's absolute path when
the spec is read, so everything after (``undream init``, the scene
directory's ``metadata.json``) sees an ordinary file. A name that is not in
the cache is one :class:`~undream.errors.SpecError` line naming the field and
telling the user to run ``./deploy/setup.sh``.
"""
from __future__ import annotations

import re
from pathlib import Path

from undream.errors import SpecError

PREFIX = "asset:"
MESH_FILE = "mesh.ply"
TEXTURE_FILE = "texture.png"
ASSET_FILE = "asset.json"
_NAME = re.compile(r"[a-z0-9][a-z0-9_]*")


def assets_root(cache_dir: str | Path) -> Path:
    """``CACHE_DIR/assets``: ``CACHE_DIR`` is undream's cache folder, ``<cache_home>/undream``
    (``LocalSettings.cache_home``, default ``~/.cache``), where ``deploy/fetch_assets.py`` writes."""
    return Path(cache_dir) / "assets"


def is_fetched(value: object) -> bool:
    """True when ``value`` is an ``asset:NAME`` reference."""
    return isinstance(value, str) and value.startswith(PREFIX)


def resolve(value: str, field: str, kind: str = "mesh", cache_dir: str | Path | None = None) -> str:
    """The absolute path of ``asset:NAME``'s ``kind`` (``mesh`` or ``texture``) in the asset cache.

    ``field`` names the spec field in errors (``mesh``, ``texture.init``).
    ``cache_dir``: undream's cache folder (:func:`assets_root`), which the edge passes from its
    settings; None (a caller that has none) is one line too. Raises :class:`SpecError` (one line)
    for a malformed name or a file the cache lacks.
    """
    name = value[len(PREFIX):]
    if not _NAME.fullmatch(name):
        raise SpecError(f"{field}: {value!r} is not an asset name (asset:NAME, NAME in lower case letters, "
                        "digits and _, e.g. asset:p406)")
    if cache_dir is None:
        raise SpecError(f"{field}: {value!r} names a fetched asset, but no asset cache was given "
                        "(undream's commands pass <cache_home>/undream/assets from their settings)")
    folder = assets_root(cache_dir) / name
    path = folder / (MESH_FILE if kind == "mesh" else TEXTURE_FILE)
    if not path.is_file():
        have = "the asset has no starting texture; give an sRGB colour or an image" \
            if kind == "texture" and (folder / MESH_FILE).is_file() \
            else "run ./deploy/setup.sh (or .venv/bin/python deploy/fetch_assets.py) to fetch and convert it"
        raise SpecError(f"{field}: {value!r} is not in the asset cache ({path} not found); {have}")
    return str(path)
