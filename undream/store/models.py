"""The run store's tables (SQLAlchemy 2 declarative, typed).

Six tables, all owned by :class:`undream.store.Store`; nothing else writes
them: runs, sweeps (a grid of runs), iteration records, frame jobs (every
per-frame job of a run: the attack's render-and-gradient jobs and the
evaluation's render-and-predict jobs), the schema version, and blobs (only
with the ``database`` blob backend). Textures, gradients and attack states are
blobs (:mod:`undream.store.blobs`) and rows hold their keys; the ``blobs``
table holds their bytes when the farm keeps its blobs in its database
(created where missing by ``create_all``, no schema step). JSON columns are text
holding strict JSON (non-finite floats are written as null).

Timestamps are UTC. Floats that are not finite are stored as NULL (SQLite turns
NaN into NULL anyway; doing it everywhere keeps both backends alike).
"""
from __future__ import annotations

import datetime as dt

from sqlalchemy import (
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from undream.runlist import RUN_STATUSES

JOB_STATUSES = ("queued", "started", "succeeded", "failed", "retried")
JOB_PHASES = ("attack", "pre", "adversarial")  # iteration jobs; evaluation before and after the final pick
SCHEMA_VERSION = 5  # 1: runs, iterations, frame_jobs without phases; 2: the farm (sweeps, scenes, phases);
#                    3: run leases (runs.owner, runs.heartbeat; migrated in place from 2);
#                    4: the control plane's indexes and the blobs table (alembic revision 0004,
#                       undream/store/migrations)
#                    5: iterations.terms_json, the objective's named terms (alembic revision 0005)

_NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> dt.datetime:
    """The current time, timezone-aware UTC."""
    return dt.datetime.now(dt.timezone.utc)


def _one_of(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=_NAMING)


class Run(Base):
    """One attack run: its config, state machine and iteration counter.

    ``iteration`` is the number of completed steps: texture ``k`` exists for
    every ``k <= iteration``. It is the compare-and-set target of
    :meth:`undream.store.Store.advance`.
    """

    __tablename__ = "runs"
    __table_args__ = (
        CheckConstraint(_one_of("status", RUN_STATUSES), name="status"),
        CheckConstraint("iteration >= 0", name="iteration"),
        CheckConstraint("n_frames >= 1", name="n_frames"),
        # A page of runs newest first, of everything, one status or one sweep (the control plane's lists)
        Index("ix_runs_created_id", "created", "id"),
        Index("ix_runs_status_created_id", "status", "created", "id"),
        Index("ix_runs_sweep_created_id", "sweep_id", "created", "id"),
        Index("ix_runs_owner", "owner"),  # the few runs a process owns, among any number of farm runs
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    config_json: Mapped[str] = mapped_column(Text)
    status: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    n_frames: Mapped[int] = mapped_column(Integer)
    seed: Mapped[int] = mapped_column(BigInteger)
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow,
                                                 onupdate=utcnow)
    error: Mapped[str | None] = mapped_column(Text)
    attack_state_ref: Mapped[str | None] = mapped_column(String(400))
    results_json: Mapped[str | None] = mapped_column(Text)
    scene_ref: Mapped[str | None] = mapped_column(String(400))  # blob key of the packed scene directory
    out_dir: Mapped[str | None] = mapped_column(Text)  # where the finish stage writes the outputs
    sweep_id: Mapped[str | None] = mapped_column(ForeignKey("sweeps.id", ondelete="SET NULL"), index=True)
    farm_json: Mapped[str] = mapped_column(Text, default="{}")  # scheduling options fixed at submit
    failures: Mapped[int] = mapped_column(Integer, default=0)  # frame jobs given up on (failure budget)
    # The lease of a run that one process drives (``undream run``): host:pid and its last heartbeat.
    # Farm runs have no owner (their jobs are redelivered by the broker instead).
    owner: Mapped[str | None] = mapped_column(String(200))
    heartbeat: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))


class Sweep(Base):
    """A grid of runs submitted together (``undream sweep``)."""

    __tablename__ = "sweeps"

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), index=True)
    spec_json: Mapped[str] = mapped_column(Text)
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class SchemaVersion(Base):
    """One row: the schema version the tables were created with (see ``SCHEMA_VERSION``)."""

    __tablename__ = "undream_schema"

    version: Mapped[int] = mapped_column(Integer, primary_key=True)


class IterationRecord(Base):
    """Metrics of step ``k`` (gradients of texture ``k`` reduced, texture ``k+1`` made).

    ``n_ok``/``n_bad``: frames kept/dropped (non-finite or failed); ``dropped_json``
    the dropped frame indexes; ``per_frame_json`` any per-frame detail the caller keeps;
    ``terms_json`` the objective's named terms when it has regularisers (``loss_victim``,
    ``loss_total``, ``reg_tv``, ...; :func:`undream.attacks.regularise.objective`).
    """

    __tablename__ = "iterations"
    __table_args__ = (UniqueConstraint("run_id", "k"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    k: Mapped[int] = mapped_column(Integer)
    loss_mean: Mapped[float | None] = mapped_column(Float)
    n_ok: Mapped[int] = mapped_column(Integer, default=0)
    n_bad: Mapped[int] = mapped_column(Integer, default=0)
    dropped_json: Mapped[str] = mapped_column(Text, default="[]")
    grad_norm: Mapped[float | None] = mapped_column(Float)
    step_seconds: Mapped[float | None] = mapped_column(Float)
    per_frame_json: Mapped[str] = mapped_column(Text, default="[]")
    terms_json: Mapped[str | None] = mapped_column(Text, nullable=True)
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class FrameJob(Base):
    """One per-frame job: frame ``frame`` (a position) of iteration ``k`` in ``phase``.

    ``phase`` ``attack``: the render-and-gradient job of iteration ``k``
    (gradient blob ``grad_ref``, ``loss``, ``finite``); ``pre`` and
    ``adversarial``: the evaluation's render-and-predict jobs (``k`` = the
    number of steps; ``result_json`` the prediction and loss, ``image_ref`` the
    rendered 8-bit frame).
    """

    __tablename__ = "frame_jobs"
    __table_args__ = (
        UniqueConstraint("run_id", "phase", "k", "frame"),
        CheckConstraint(_one_of("status", JOB_STATUSES), name="status"),
        CheckConstraint(_one_of("phase", JOB_PHASES), name="phase"),
        # A run's jobs at its current iteration, whatever the phase: the stuck-run and progress reads
        Index("ix_frame_jobs_run_k_status", "run_id", "k", "status"),
        # The few jobs with an error, found without reading the others (failing runs)
        Index("ix_frame_jobs_failed", "run_id", sqlite_where=text("error IS NOT NULL"),
              postgresql_where=text("error IS NOT NULL")),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    phase: Mapped[str] = mapped_column(String(16), default="attack")
    k: Mapped[int] = mapped_column(Integer)
    frame: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    loss: Mapped[float | None] = mapped_column(Float)
    finite: Mapped[bool] = mapped_column(Boolean, default=False)
    grad_ref: Mapped[str | None] = mapped_column(String(400))
    timings_json: Mapped[str] = mapped_column(Text, default="{}")
    error: Mapped[str | None] = mapped_column(Text)
    result_json: Mapped[str | None] = mapped_column(Text)
    image_ref: Mapped[str | None] = mapped_column(String(400))
    worker: Mapped[str | None] = mapped_column(String(200))  # host:pid of the last attempt
    started: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    finished: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))


class Blob(Base):
    """One blob of the ``database`` blob backend (:mod:`undream.store.blob_db`): its bytes by key.

    ``used``: when it was last written or read by the transport cache (least
    recently used evicted first). The key column compares bytewise on
    PostgreSQL (collation ``C``), so a key prefix is an index range.
    """

    __tablename__ = "blobs"

    key: Mapped[str] = mapped_column(String(1024).with_variant(String(1024, collation="C"), "postgresql"),
                                     primary_key=True)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    size: Mapped[int] = mapped_column(BigInteger)
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    used: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
