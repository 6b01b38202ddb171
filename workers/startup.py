"""A worker's start: it waits for the farm's run database, and refuses one that is not the farm's.

``undream worker`` opens the farm's store before it consumes anything
(:func:`wait_for_store`):

- A PostgreSQL server that does not answer (a database restarting, or
  started after the workers) is waited for, with a line saying so at each
  try (1, 2, 4 … 30 s apart), as Celery waits for its broker; before, the
  worker exited.
- A database without the farm's tables (a SQLite file not there yet, an
  empty PostgreSQL database) is made, as before, on a new farm: nothing was
  submitted yet. But where the farm's blob store already holds packed
  scenes (every submitted run has one), a database without the farm's
  tables is not the farm's: a worker pointed at ``sqlite:///elsewhere.db``
  made that file and took real runs' start messages, finding none of them.
  It is refused in one line (:class:`NotTheFarm`), and nothing is created.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable

from undream.errors import StoreError
from undream.store import BlobOptions, BlobStore, NoDatabase, mask_url, open_farm_store, parse_blob_url
from undream.store.blob_s3 import S3Backend  # imports boto3 only when it makes a client
from undream.store.db import check_database

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import Store

FIRST_WAIT_S, LONGEST_WAIT_S = 1.0, 30.0
SCENES = "scenes"  # the blob prefix every submitted run's packed scene lives under


class NotTheFarm(StoreError):
    """The database has none of the farm's tables, but the farm's blob store holds its scenes."""


class Unreachable(StoreError):
    """The run database's server does not answer (yet)."""


def _farm_blobs(settings: "Settings") -> BlobStore | None:
    """The settings' blob store where it is not the database itself (None: ``database`` blobs)."""
    parsed = parse_blob_url(settings.blob_url)
    if parsed.kind == "database":
        return None
    if parsed.kind == "folder":
        return BlobStore(parsed.root) if parsed.root is not None and parsed.root.is_dir() else None
    return BlobStore(S3Backend(parsed.bucket, parsed.prefix, BlobOptions.of(settings)))


def refuse_if_not_the_farms(settings: "Settings") -> None:
    """NotTheFarm when the blob store holds packed scenes (so a farm submitted runs) while the
    database has none of its tables; nothing is created either way."""
    blobs = _farm_blobs(settings)
    if blobs is None:
        return
    try:
        scenes = blobs.listing(SCENES)
    finally:
        blobs.close()
    if scenes:
        url = settings.database_url
        name = f"database_url {mask_url(url)!r}" if url else "database_url (unset: the SQLite file of the blob folder)"
        raise NotTheFarm(f"{name}: not the farm's database (none of the farm's tables, while blob_url "
                         f"{settings.blob_url!r} holds {len(scenes)} packed scene(s) of its runs); give the "
                         "farm's --database (UNDREAM_DATABASE_URL); nothing was created")


def farm_store(settings: "Settings") -> "Store":
    """The farm's store for a worker: Unreachable while the server does not answer; the tables
    made on a new farm; NotTheFarm (nothing created) for a database that is not the farm's."""
    url = settings.database_url
    if url is not None and not url.startswith("sqlite"):
        try:
            check_database(url)
        except StoreError as err:
            raise Unreachable(str(err)) from None
    try:
        return open_farm_store(settings, create=False)
    except NoDatabase:
        refuse_if_not_the_farms(settings)
    return open_farm_store(settings)


def wait_for_store(settings: "Settings", say: Callable[[str], None],
                   sleep: Callable[[float], None] = time.sleep) -> "Store":
    """:func:`farm_store`, tried again while the database does not answer, with a line (``say``)
    before each wait; any other StoreError (NotTheFarm, a newer schema) is raised at once."""
    wait = FIRST_WAIT_S
    while True:
        try:
            return farm_store(settings)
        except Unreachable as err:
            say(f"undream worker: waiting for the run database: {err}; trying again in {wait:g} s")
            sleep(wait)
            wait = min(2 * wait, LONGEST_WAIT_S)
