"""Opening the run store: database engine (SQLite or PostgreSQL) plus blob backend.

Database URLs:

- ``None`` → SQLite at ``<blob folder>/undream.db`` (the embedded default; a
  folder blob URL only: with ``database`` or ``s3://`` blobs there is no folder
  to put it in, and a StoreError says to set ``database_url``).
- ``sqlite:///path/to.db`` → SQLite in WAL mode with foreign keys on, a 30 s
  busy timeout, and ``BEGIN IMMEDIATE`` for write transactions so that
  concurrent writers queue instead of failing.
- ``postgresql://user:password@host:port/db`` (or ``postgres://``,
  ``postgresql+psycopg://``) → PostgreSQL through psycopg 3 (install the
  ``postgres`` extra), with pre-ping and a connect timeout.

Blob URLs (:func:`undream.store.blobs.parse_blob_url`): a folder, ``database``
(the ``blobs`` table of this database, :mod:`undream.store.blob_db`) or
``s3://bucket/prefix`` (:mod:`undream.store.blob_s3`, with
:class:`undream.store.blobs.BlobOptions` for the endpoint and keys).

Engines hold connections: open the store in each worker process after the
fork, never before.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine, create_engine, event, func, inspect, insert, select, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError, SQLAlchemyError
from sqlalchemy.pool import StaticPool

from undream.errors import StoreError
from undream.redact import redact
from undream.store.blob_db import DatabaseBackend
from undream.store.blob_s3 import S3Backend  # imports boto3 only when it makes a client
from undream.store.blobs import DATABASE, BlobOptions, BlobStore, BlobURL, parse_blob_url
from undream.store.models import SCHEMA_VERSION, Base, SchemaVersion
from undream.store.store import WRITE_OPTION, Store, db_reason

if TYPE_CHECKING:
    from alembic.config import Config as AlembicConfig
    from undream.settings import Settings

SQLITE_FILENAME = "undream.db"
CONNECT_TIMEOUT_S = 10
_VALID = "valid URLs are sqlite:///path/to/undream.db or postgresql://user:password@host:port/database"
_CREATE_LOCK = 0x756E6472  # PostgreSQL advisory lock id held while creating tables ("undr")


def mask_url(url: str) -> str:
    """``url`` with its password replaced by ``***``, parseable or not, whatever characters the
    password holds (:func:`undream.redact.redact`: not SQLAlchemy's reading alone, which shows the
    ``ss`` of ``redis://:p@ss@host`` as part of the host)."""
    return str(redact(url))


def _parse(url: str) -> URL:
    try:
        parsed = make_url(url)
        _ = parsed.port  # a non-numeric port fails here, not later
    except (ArgumentError, ValueError) as exc:
        raise StoreError(f"database URL {mask_url(url)!r} is malformed ({exc}); {_VALID}") from None
    backend = parsed.get_backend_name()
    if backend == "postgres":
        backend = "postgresql"
    if backend == "postgresql":
        return parsed.set(drivername="postgresql+psycopg")
    if backend == "sqlite":
        return parsed
    raise StoreError(f"database URL {mask_url(url)!r}: unsupported backend {backend!r}; {_VALID}")


def _sqlite_engine(url: URL) -> Engine:
    memory = url.database in (None, "", ":memory:")
    kwargs: dict[str, Any] = {"connect_args": {"check_same_thread": False, "timeout": 30}}
    if memory:
        kwargs["poolclass"] = StaticPool
    engine = create_engine(url, **kwargs)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        dbapi_conn.isolation_level = None  # we emit BEGIN ourselves (below)
        cur = dbapi_conn.cursor()
        if not memory:
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=NORMAL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute("PRAGMA busy_timeout=30000")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Any) -> None:
        conn.exec_driver_sql(conn.get_execution_options().get(WRITE_OPTION, "BEGIN"))

    return engine


def make_engine(url: str) -> Engine:
    """An engine for ``url`` with undream's settings (see the module docstring)."""
    parsed = _parse(url)
    try:
        if parsed.get_backend_name() == "sqlite":
            return _sqlite_engine(parsed)
        return create_engine(parsed, pool_pre_ping=True,
                             connect_args={"connect_timeout": CONNECT_TIMEOUT_S})
    except (NoSuchModuleError, ModuleNotFoundError) as exc:
        raise StoreError(f"database URL {mask_url(url)!r}: driver missing ({exc}); "
                         "install undream[postgres] for PostgreSQL") from None


SQLITE_HEADER = b"SQLite format 3\x00"


def check_database(url: str) -> None:
    """StoreError (one line, password hidden) unless the database of ``url`` can be used: a SQLite
    file's folder exists and the file, if any, is a SQLite database; a server answers. Nothing is
    created: a command checks this before it writes anything."""
    parsed = _parse(url)
    if parsed.get_backend_name() == "sqlite" and parsed.database not in (None, "", ":memory:"):
        path = Path(parsed.database)
        if not path.parent.is_dir():
            raise StoreError(f"database URL {mask_url(url)!r}: the folder {path.parent} does not exist")
        if path.exists():
            with open(path, "rb") as f:
                if f.read(len(SQLITE_HEADER)) not in (SQLITE_HEADER, b""):
                    raise StoreError(f"database URL {mask_url(url)!r}: {path} is not a SQLite database")
        return
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except SQLAlchemyError as exc:
        raise StoreError(f"cannot reach the run database at {mask_url(url)!r}: {db_reason(exc)}") from None
    finally:
        engine.dispose()


def _schema_version(conn: Any) -> int | None:
    """The schema version of the tables there, None for an empty database (1: before versions)."""
    names = set(inspect(conn).get_table_names())
    if SchemaVersion.__tablename__ in names:
        return conn.scalar(select(func.max(SchemaVersion.version)))
    return 1 if "runs" in names else None


def _add_columns(conn: Any, table: str, names: tuple[str, ...]) -> None:
    """``ALTER TABLE table ADD COLUMN`` for each of ``names``, typed as the model declares them."""
    columns = Base.metadata.tables[table].c
    for name in names:
        kind = columns[name].type.compile(dialect=conn.dialect)
        conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {name} {kind}"))


# Hand-written upgrades of the databases made before alembic: version → what turns a database of
# that version into the next one, up to LEGACY_VERSION; alembic's revisions take it from there.
LEGACY_VERSION = 3
MIGRATIONS = {2: lambda conn: _add_columns(conn, "runs", ("owner", "heartbeat"))}
MIGRATIONS_DIR = Path(__file__).with_name("migrations")


def _alembic(conn: Any) -> "AlembicConfig":
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.attributes["connection"] = conn
    return cfg


def _revision(conn: Any) -> str | None:
    """The alembic revision the database is at; None when it has none (new, or made before alembic)."""
    from alembic.runtime.migration import MigrationContext

    return MigrationContext.configure(conn).get_current_revision()


def _migrate(conn: Any, found: int, url: str) -> None:
    """Upgrade tables of schema ``found`` to ``SCHEMA_VERSION`` in the caller's transaction: the
    hand-written steps up to ``LEGACY_VERSION``, then alembic's revisions (``undream/store/migrations``)."""
    from alembic import command

    for version in range(found, LEGACY_VERSION):
        if version not in MIGRATIONS:
            raise StoreError(
                f"the run database at {mask_url(url)!r} has schema version {found}, this undream "
                f"needs version {SCHEMA_VERSION} and cannot upgrade from {version}; use a new database")
        MIGRATIONS[version](conn)
        conn.execute(insert(SchemaVersion).values(version=version + 1))
    cfg = _alembic(conn)
    if _revision(conn) is None:
        command.stamp(cfg, f"{max(found, LEGACY_VERSION):04d}")
    command.upgrade(cfg, "head")
    conn.execute(insert(SchemaVersion).values(version=SCHEMA_VERSION))


class NoDatabase(StoreError):
    """There is no farm database where the settings point (a command that only reads or changes
    existing runs creates none)."""

    def __init__(self, where: str, why: str = "") -> None:
        super().__init__(f"no farm database at {where!r}{f' ({why})' if why else ''}: nothing was "
                         "submitted to this farm yet, or give its --database and --blobs "
                         "(UNDREAM_DATABASE_URL, UNDREAM_BLOB_URL)")


def create_tables(engine: Engine, url: str, create: bool = True) -> None:
    """Create the store's tables if missing, upgrade older ones, and check their schema version.

    Tables of an older schema are upgraded in place, in one transaction
    (:func:`_migrate`: 2 → 3 adds the run lease columns, 3 → 4 the runs lists' indexes). StoreError naming the
    URL (password hidden) when the database is unreachable, or when its
    tables were made by a newer undream or by one too old to upgrade.
    ``create`` False: a database without undream's tables is :class:`NoDatabase`
    and stays as it is.
    """
    try:
        with engine.execution_options(**{WRITE_OPTION: "BEGIN IMMEDIATE"}).begin() as conn:
            if engine.dialect.name == "postgresql":
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _CREATE_LOCK})
            found = _schema_version(conn)
            if found is None and not create:
                raise NoDatabase(mask_url(url), "no undream tables there")
            if found is not None and found > SCHEMA_VERSION:
                raise StoreError(
                    f"the run database at {mask_url(url)!r} has schema version {found}, newer than "
                    f"this undream's {SCHEMA_VERSION}; upgrade undream")
            if found is not None and found < SCHEMA_VERSION:
                _migrate(conn, found, url)
            Base.metadata.create_all(conn)
            if found is None:
                conn.execute(insert(SchemaVersion).values(version=SCHEMA_VERSION))
                from alembic import command

                command.stamp(_alembic(conn), "head")
    except SQLAlchemyError as exc:
        reason = db_reason(exc)
        password = make_url(url).password
        if password:
            reason = reason.replace(str(password), "***")
        raise StoreError(f"cannot open the run database at {mask_url(url)!r}: {reason}") from None


def _sqlite_file(url: str) -> Path | None:
    """The file of a SQLite URL; None for another backend, an in-memory database or a SQLite URI
    filename (``?uri=true``: its own ``mode`` says whether it may create the file)."""
    parsed = _parse(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:") \
            or parsed.query.get("uri"):
        return None
    return Path(parsed.database)


def _no_folder(blob_url: BlobURL) -> StoreError:
    shown = DATABASE if blob_url.kind == "database" else f"s3://{blob_url.bucket}/{blob_url.prefix}"
    return StoreError(f"database_url: not set, and blob_url {shown!r} is no folder to keep the default "
                      "SQLite file in; set database_url (UNDREAM_DATABASE_URL: sqlite:///path/undream.db "
                      "on one machine, postgresql://... for a farm)")


def _blob_store(parsed: BlobURL, engine: Engine, options: BlobOptions) -> BlobStore:
    if parsed.kind == "folder":
        return BlobStore(parsed.root, options.local_dir)  # type: ignore[arg-type]
    if parsed.kind == "database":
        return BlobStore(DatabaseBackend(engine), options.local_dir)
    return BlobStore(S3Backend(parsed.bucket, parsed.prefix, options), options.local_dir)


def open_store(url: str | None, blob_dir: Path | str, create: bool = True,
               options: BlobOptions | None = None) -> Store:
    """Open (creating tables and folders as needed) the run store.

    ``url``: database URL, or None for SQLite at ``<blob folder>/undream.db``
    (a folder blob URL only). ``blob_dir``: the blob URL (see the module
    docstring): a folder (or ``file:///`` URL) shared by every process of the
    farm, ``database`` or ``s3://bucket/prefix``. ``options``: the S3 endpoint
    and keys, and the local folder for blob copies (:class:`BlobOptions`;
    :func:`open_farm_store` fills them from the settings). ``create`` False
    (the commands that read the farm, or change a run it holds): nothing is
    created, neither folder, file nor table; :class:`NoDatabase` (one line,
    the URL's password hidden) when there is no farm database.
    """
    parsed = parse_blob_url(blob_dir)
    options = options or BlobOptions()
    blob_root = parsed.root
    if create and blob_root is not None:
        try:
            blob_root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"blob folder {str(blob_root)!r}: cannot create it: {exc}") from exc
    where = None
    if url is None:
        if blob_root is None:
            raise _no_folder(parsed)
        url = f"sqlite:///{(blob_root / SQLITE_FILENAME).resolve()}"
        where = str((blob_root / SQLITE_FILENAME).resolve())
    sqlite_file = _sqlite_file(url)
    if not create and sqlite_file is not None and not sqlite_file.is_file():
        raise NoDatabase(where or mask_url(url))  # SQLite would create the file on connecting
    engine = make_engine(url)
    try:
        create_tables(engine, url, create)
        return Store(engine, _blob_store(parsed, engine, options))
    except StoreError:
        engine.dispose()
        raise


def open_farm_store(settings: "Settings", create: bool = True) -> Store:
    """:func:`open_store` for a farm's settings: its database, blob URL and blob options."""
    return open_store(settings.database_url, settings.blob_url, create, BlobOptions.of(settings))
