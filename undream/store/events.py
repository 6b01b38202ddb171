"""A run's events: one-line notes of what the farm did to a run by itself (a heal, a re-plan).

Each event is a small JSON blob under ``runs/<id>/events/`` whose key starts
with its UTC time, so a listing reads them in order; writing one also moves
the run's ``updated`` (an event is a change of the run: the farm's stall
rule, :mod:`scheduler.heal`, counts from it, so a run it healed is not
healed again before its threshold). No table: events are as rare as stalls,
and a run's blobs go with it (:meth:`undream.store.Store.delete_run`).
"""
from __future__ import annotations

import datetime as dt
import uuid
from typing import TYPE_CHECKING, NamedTuple

from sqlalchemy import update

from undream.errors import StoreError
from undream.store.blobs import BlobStore, event_prefix
from undream.store.models import Run, utcnow

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from sqlalchemy.orm import Session

MAX_LINE = 500  # characters an event line keeps


class RunEvent(NamedTuple):
    """One event of a run: when (UTC), who (``host:pid``, or a command's name) and what, in one line."""

    time: dt.datetime
    by: str
    line: str


class EventMethods:
    """The event methods of :class:`undream.store.Store` (a mixin: needs ``_tx`` and ``blobs``)."""

    blobs: BlobStore

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    def add_event(self, run_id: str, line: str, by: str) -> RunEvent:
        """Record ``line`` (one line, cut to ``MAX_LINE`` characters) as an event of the run, by
        ``by``, and move the run's ``updated`` to now; StoreError if there is no such run."""
        if not isinstance(line, str) or not line.strip():
            raise StoreError(f"event line: must be a non-empty string, got {line!r}")
        event = RunEvent(utcnow(), str(by), " ".join(line.split())[:MAX_LINE])
        with self._tx("add_event", write=True) as s:
            moved = s.execute(update(Run).where(Run.id == run_id).values(updated=event.time)
                              .execution_options(synchronize_session=False)).rowcount
            if moved != 1:
                raise StoreError(f"run {run_id!r}: not found")
            key = f"{event_prefix(run_id)}/{event.time:%Y%m%dT%H%M%S%f}-{uuid.uuid4().hex[:8]}.json"
            self.blobs.put_json(key, {"time": event.time.isoformat(), "by": event.by, "line": event.line})
        return event

    def events(self, run_id: str, limit: int | None = None) -> list[RunEvent]:
        """The run's events, oldest first (the last ``limit`` of them, if given)."""
        keys = sorted(info.key for info in self.blobs.listing(event_prefix(run_id)))
        out = []
        for key in keys[-limit:] if limit else keys:
            doc = self.blobs.get_json(key)
            out.append(RunEvent(dt.datetime.fromisoformat(doc["time"]), doc["by"], doc["line"]))
        return out
