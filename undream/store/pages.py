"""Runs read a page at a time: the control plane's lists at any farm size.

A page is the runs newest first (``created``, then ``id``, both descending;
or oldest first, a sweep's grid order), filtered by status and sweep, after a
*cursor*: an opaque string naming the last run of the previous page. Paging
newest first never repeats or skips a run that was there when it began (new
runs sort before the first page). Each page is one indexed query (schema 4's ``ix_runs_*_created_id``),
plus one count; the per-status and per-sweep tallies are one grouped query
each. Nothing here reads a run's jobs (see :meth:`Store.job_counts` for a
page's progress).
"""
from __future__ import annotations

import base64
import binascii
import datetime as dt
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

from sqlalchemy import ColumnElement, and_, func, or_, select

from undream.errors import StoreError
from undream.runlist import MAX_PAGE
from undream.store.jobs import IN_CHUNK
from undream.store.models import RUN_STATUSES, Run, Sweep
from undream.store.snapshots import RunSnapshot, SweepSnapshot

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from sqlalchemy.orm import Session



class BadCursor(StoreError):
    """A cursor that no page of this list gave (the caller's mistake, not the database's)."""


@dataclass(frozen=True)
class RunPage:
    """One page of runs, newest first: ``next`` is the cursor of the page after it (None: the last
    page); ``total`` counts every run the filters match, on every page."""

    runs: list[RunSnapshot]
    next: str | None
    total: int


def encode_cursor(run: RunSnapshot) -> str:
    """The cursor that pages on after ``run``."""
    text = f"{run.created.astimezone(dt.timezone.utc).isoformat()}|{run.id}"
    return base64.urlsafe_b64encode(text.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[dt.datetime, str]:
    """(created, id) of a cursor from :func:`encode_cursor`; :class:`BadCursor` naming it when it is not one."""
    try:
        text = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        stamp, run_id = text.split("|", 1)
        created = dt.datetime.fromisoformat(stamp)
    except (binascii.Error, UnicodeDecodeError, ValueError):
        raise BadCursor(f"cursor {cursor[:60]!r}: not a cursor of this list; page from the first page "
                         "and pass on the 'next' each page gives") from None
    if created.tzinfo is None or not run_id:
        raise BadCursor(f"cursor {cursor[:60]!r}: not a cursor of this list")
    return created.astimezone(dt.timezone.utc), run_id


def _filters(status: str | None, sweep_id: str | None) -> list[ColumnElement[bool]]:
    where = []
    if status is not None:
        if status not in RUN_STATUSES:
            raise StoreError(f"status: {status!r} is not a run status; valid statuses are "
                             f"{', '.join(RUN_STATUSES)}")
        where.append(Run.status == status)
    if sweep_id is not None:
        where.append(Run.sweep_id == sweep_id)
    return where


class ListMethods:
    """The paged reads of :class:`undream.store.Store` (a mixin: needs ``_tx``)."""

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    def runs_page(self, status: str | None = None, sweep_id: str | None = None, limit: int | None = 50,
                  after: str | None = None, newest_first: bool = True) -> RunPage:
        """Up to ``limit`` runs (with ``status``, of sweep ``sweep_id``) newest first (or oldest
        first: a sweep's runs in grid order), after the cursor ``after``; ``limit`` None: every run
        from there on (a CSV export)."""
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int)
                                  or not 1 <= limit <= MAX_PAGE):
            raise StoreError(f"limit: must be a whole number from 1 to {MAX_PAGE}, got {limit!r}")
        where = _filters(status, sweep_id)
        query = select(Run).where(*where)
        if after:
            created, run_id = decode_cursor(after)
            if newest_first:
                query = query.where(or_(Run.created < created, and_(Run.created == created, Run.id < run_id)))
            else:
                query = query.where(or_(Run.created > created, and_(Run.created == created, Run.id > run_id)))
        query = query.order_by(*((Run.created.desc(), Run.id.desc()) if newest_first else (Run.created, Run.id)))
        if limit is not None:
            query = query.limit(limit + 1)
        with self._tx("runs_page", write=False) as s:
            rows = [RunSnapshot.of(r) for r in s.scalars(query)]
            total = s.scalar(select(func.count()).select_from(Run).where(*where)) or 0
        more = limit is not None and len(rows) > limit
        runs = rows[:limit] if more else rows
        return RunPage(runs=runs, next=encode_cursor(runs[-1]) if more else None, total=total)

    def status_counts(self, sweep_id: str | None = None) -> dict[str, int]:
        """Status → number of runs (of sweep ``sweep_id``), in one grouped query; statuses without
        runs are left out."""
        query = select(Run.status, func.count()).where(*_filters(None, sweep_id)).group_by(Run.status)
        with self._tx("status_counts", write=False) as s:
            return {status: n for status, n in s.execute(query)}

    def sweep_counts(self, sweep_ids: Sequence[str] | None = None) -> dict[str, dict[str, int]]:
        """Sweep id → status → number of runs, for every sweep that has runs (or ``sweep_ids``), in
        one grouped query."""
        query = select(Run.sweep_id, Run.status, func.count()).where(Run.sweep_id.is_not(None))
        if sweep_ids is not None:
            query = query.where(Run.sweep_id.in_(list(sweep_ids)))
        out: dict[str, dict[str, int]] = {}
        with self._tx("sweep_counts", write=False) as s:
            for sweep_id, status, n in s.execute(query.group_by(Run.sweep_id, Run.status)):
                out.setdefault(sweep_id, {})[status] = n
        return out

    def sweeps_of(self, sweep_ids: Sequence[str], limit: int | None = None) -> list[SweepSnapshot]:
        """The sweeps ``sweep_ids`` (the newest ``limit`` of them), newest first, in one query per
        :data:`IN_CHUNK` ids."""
        ids, out = list(dict.fromkeys(sweep_ids)), []
        with self._tx("sweeps_of", write=False) as s:
            for i in range(0, len(ids), IN_CHUNK):
                out += [SweepSnapshot.of(r) for r in s.scalars(select(Sweep).where(Sweep.id.in_(ids[i:i + IN_CHUNK])))]
        out.sort(key=lambda sweep: (sweep.created, sweep.id), reverse=True)
        return out if limit is None else out[:limit]
