"""The run store's tables (SQLAlchemy 2 declarative, typed).

Three tables, all owned by :class:`undream.store.Store`; nothing else writes
them. Arrays never live here: textures, gradients and attack states are blobs
(:mod:`undream.store.blobs`) and rows hold their keys. JSON columns are text
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
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

RUN_STATUSES = ("queued", "running", "evaluating", "done", "failed", "cancelled")
JOB_STATUSES = ("queued", "started", "succeeded", "failed", "retried")

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


class IterationRecord(Base):
    """Metrics of step ``k`` (gradients of texture ``k`` reduced, texture ``k+1`` made).

    ``n_ok``/``n_bad``: frames kept/dropped (non-finite or failed); ``dropped_json``
    the dropped frame indexes; ``per_frame_json`` any per-frame detail the caller keeps.
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
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class FrameJob(Base):
    """One render-and-gradient job: frame ``frame`` of iteration ``k``."""

    __tablename__ = "frame_jobs"
    __table_args__ = (
        UniqueConstraint("run_id", "k", "frame"),
        CheckConstraint(_one_of("status", JOB_STATUSES), name="status"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    k: Mapped[int] = mapped_column(Integer)
    frame: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16), default="queued")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    loss: Mapped[float | None] = mapped_column(Float)
    finite: Mapped[bool] = mapped_column(Boolean, default=False)
    grad_ref: Mapped[str | None] = mapped_column(String(400))
    timings_json: Mapped[str] = mapped_column(Text, default="{}")
    error: Mapped[str | None] = mapped_column(Text)
    started: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    finished: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
