"""The ``database`` blob backend: blobs as rows of the run database's ``blobs`` table.

A small farm then needs only Redis and the database (SQLite on one machine,
PostgreSQL for several): no shared folder. A write is one upsert
(``INSERT … ON CONFLICT (key) DO UPDATE``), so writing a key twice leaves one
row with the last bytes and a reader sees the old row or the new, never part.

Inside a write transaction of :class:`undream.store.Store` (``advance``,
``start_run``) the blob writes go through that transaction's connection
(:meth:`DatabaseBackend.bind`): the texture, attack state and iteration
record of a step commit together, and a SQLite writer never waits on itself.
"""
from __future__ import annotations

import datetime as dt
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from sqlalchemy import Engine, delete, func, or_, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import SQLAlchemyError

from undream.errors import StoreError
from undream.store.blob_backends import BlobInfo, BlobMissing
from undream.store.models import Blob, utcnow
from undream.store.store import WRITE_OPTION, db_reason

_CHUNK = 500  # keys per DELETE … IN (...)


class DatabaseBackend:
    """Blob bytes in the ``blobs`` table of ``engine``'s database (see the module docstring)."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self._writer = engine.execution_options(**{WRITE_OPTION: "BEGIN IMMEDIATE"})
        self._bound = threading.local()
        url = engine.url.render_as_string(hide_password=True)
        self.where = f"blobs table of the run database {url!r}"

    @contextmanager
    def bind(self, conn: Any) -> Iterator[None]:
        """Route this thread's blob reads and writes through ``conn`` (a transaction's connection)."""
        previous = getattr(self._bound, "conn", None)
        self._bound.conn = conn
        try:
            yield
        finally:
            self._bound.conn = previous

    @contextmanager
    def _conn(self, op: str, key: str, write: bool) -> Iterator[Any]:
        bound = getattr(self._bound, "conn", None)
        try:
            if bound is not None:
                yield bound
                return
            with (self._writer if write else self.engine).begin() as conn:
                yield conn
        except SQLAlchemyError as exc:
            raise StoreError(f"blob {key!r}: cannot {op} it in the {self.where}: {db_reason(exc)}") from exc

    @property
    def _dialect(self) -> Any:
        return postgresql if self.engine.dialect.name == "postgresql" else sqlite

    @staticmethod
    def _under(prefix: str) -> Any:
        return or_(Blob.key == prefix, Blob.key.startswith(prefix + "/", autoescape=True))

    def write(self, key: str, data: bytes, durable: bool = True) -> None:  # the database commits it
        now = utcnow()
        stmt = self._dialect.insert(Blob).values(key=key, data=data, size=len(data), created=now, used=now)
        stmt = stmt.on_conflict_do_update(index_elements=["key"], set_={
            "data": stmt.excluded.data, "size": stmt.excluded.size, "created": stmt.excluded.created,
            "used": stmt.excluded.used})
        with self._conn("write", key, write=True) as conn:
            conn.execute(stmt)

    def write_file(self, key: str, src: Path) -> int:
        data = Path(src).read_bytes()
        self.write(key, data)
        return len(data)

    def _column(self, op: str, key: str, column: Any) -> Any:
        """``column`` of blob ``key``; BlobMissing when there is none."""
        with self._conn(op, key, write=False) as conn:
            value = conn.scalar(select(column).where(Blob.key == key))
        if value is None:
            raise BlobMissing(key)
        return value

    def read(self, key: str) -> bytes:
        return bytes(self._column("read", key, Blob.data))

    def local_path(self, key: str) -> Path | None:
        return None

    def exists(self, key: str) -> bool:
        with self._conn("look up", key, write=False) as conn:
            return conn.scalar(select(func.count()).where(Blob.key == key)) == 1

    def size(self, key: str) -> int:
        return int(self._column("look up", key, Blob.size))

    def listing(self, prefix: str) -> list[BlobInfo]:
        with self._conn("list", prefix, write=False) as conn:
            rows = conn.execute(select(Blob.key, Blob.size, Blob.used).where(self._under(prefix))
                                .order_by(Blob.key)).all()
        return [BlobInfo(k, int(s), u if u.tzinfo else u.replace(tzinfo=dt.timezone.utc)) for k, s, u in rows]

    def touch(self, key: str) -> None:
        with self._conn("touch", key, write=True) as conn:
            conn.execute(update(Blob).where(Blob.key == key).values(used=utcnow()))

    def delete_prefix(self, prefix: str) -> int:
        with self._conn("delete", prefix, write=True) as conn:
            return conn.execute(delete(Blob).where(self._under(prefix))).rowcount

    def delete(self, keys: list[str]) -> None:
        for i in range(0, len(keys), _CHUNK):
            with self._conn("delete", keys[i], write=True) as conn:
                conn.execute(delete(Blob).where(Blob.key.in_(keys[i:i + _CHUNK])))

    def check_writable(self) -> None:
        try:
            with self._writer.connect() as conn:
                tx = conn.begin()
                conn.execute(self._dialect.insert(Blob).values(key=".probe", data=b"", size=0)
                             .on_conflict_do_nothing())
                tx.rollback()
        except SQLAlchemyError as exc:
            raise StoreError(f"{self.where}: cannot write a blob there ({db_reason(exc)}); the farm's "
                             "processes write textures and gradients there") from None

    def close(self) -> None:
        pass  # the engine is the store's: Store.close disposes of it
