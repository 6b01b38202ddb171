"""Run leases in the store: which process drives a run, and when it last said so.

A run that one process drives (``undream run``) is *owned*: its row holds the
owner (``host:pid``) and a heartbeat the owner refreshes every few seconds.
When the owner dies, nothing else would ever move the run out of
``running``; the stale-run rule (:mod:`scheduler.lease`) decides from the
owner and the heartbeat's age that it is gone and fails the run with
:meth:`LeaseMethods.expire`, a compare-and-set that loses to a late heartbeat.
Farm runs have no owner: the broker redelivers the jobs of a lost worker.

All times are timezone-aware UTC.
"""
from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING

from sqlalchemy import or_, select, update

from undream.errors import StoreError
from undream.runlist import ACTIVE_STATUSES
from undream.store.models import Run, utcnow
from undream.store.snapshots import RunSnapshot

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from sqlalchemy.orm import Session

LIVE = ACTIVE_STATUSES  # statuses in which a run can be owned


def _owner(owner: object) -> str:
    if not isinstance(owner, str) or not owner.strip() or len(owner) > 200:
        raise StoreError(f"owner: must be a non-empty string of at most 200 characters "
                         f"(host:pid), got {owner!r}")
    return owner


class LeaseMethods:
    """The lease methods of :class:`undream.store.Store` (a mixin: needs ``_tx`` and ``_run``)."""

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    @staticmethod
    def _run(session: "Session", run_id: str) -> Run:  # pragma: no cover
        raise NotImplementedError

    def claim(self, run_id: str, owner: str, stale_before: dt.datetime | None = None) -> bool:
        """Make ``owner`` the run's owner, with a heartbeat now.

        Succeeds when the run has no owner, is owned by ``owner`` already, or
        its owner's last heartbeat is older than ``stale_before`` (a lease
        taken over). False, with nothing written, when another owner holds it.
        """
        owner = _owner(owner)
        with self._tx("claim", write=True) as s:
            self._run(s, run_id)
            free = or_(Run.owner.is_(None), Run.owner == owner)
            if stale_before is not None:
                free = or_(free, Run.heartbeat.is_(None), Run.heartbeat < stale_before)
            result = s.execute(update(Run).where(Run.id == run_id, free)
                               .values(owner=owner, heartbeat=utcnow())
                               .execution_options(synchronize_session=False))
            return result.rowcount == 1

    def owned_runs(self) -> list[RunSnapshot]:
        """The live runs that a process owns (``undream run``'s), oldest first: the only runs the
        stale-run rule looks at (farm runs have no owner), read without touching the others."""
        query = select(Run).where(Run.owner > "")  # a range of the owner index (every owner is non-empty)
        with self._tx("owned_runs", write=False) as s:
            runs = [RunSnapshot.of(r) for r in s.scalars(query) if r.status in LIVE]
        return sorted(runs, key=lambda run: (run.created, run.id))

    def beat(self, run_id: str, owner: str) -> bool:
        """Refresh the heartbeat of ``owner``'s run; False when ``owner`` no longer holds it."""
        owner = _owner(owner)
        with self._tx("beat", write=True) as s:
            result = s.execute(update(Run).where(Run.id == run_id, Run.owner == owner)
                               .values(heartbeat=utcnow()).execution_options(synchronize_session=False))
            return result.rowcount == 1

    def release(self, run_id: str, owner: str) -> bool:
        """Give up ``owner``'s lease (the run keeps its status); False when it held none."""
        owner = _owner(owner)
        with self._tx("release", write=True) as s:
            result = s.execute(update(Run).where(Run.id == run_id, Run.owner == owner)
                               .values(owner=None).execution_options(synchronize_session=False))
            return result.rowcount == 1

    def expire(self, run_id: str, owner: str, beat_before: dt.datetime, reason: str) -> bool:
        """Fail a run whose owner is gone: only if it is still live, still owned by ``owner``
        and its heartbeat is still older than ``beat_before`` (compare-and-set; a heartbeat
        that came in since wins). The run's error becomes ``reason``; its lease is cleared."""
        owner = _owner(owner)
        with self._tx("expire", write=True) as s:
            result = s.execute(
                update(Run).where(Run.id == run_id, Run.owner == owner, Run.status.in_(LIVE),
                                  or_(Run.heartbeat.is_(None), Run.heartbeat < beat_before))
                .values(status="failed", error=reason, owner=None)
                .execution_options(synchronize_session=False))
            return result.rowcount == 1
