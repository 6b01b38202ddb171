"""The farm's activity as the store sees it, each read in a fixed number of queries.

:meth:`ActivityTables.worker_activity` reads what the workers did in a
window (two grouped queries, whatever the number of runs);
:meth:`ActivityTables.stalled_runs` counts the farm's active runs by what
they wait for and lists those of some kinds stalled longest, and
:meth:`ActivityTables.failing_runs` the runs with a failed job at their
current iteration (two queries each). Both join
``frame_jobs`` to ``runs`` on the run id, so only the jobs of the runs that
matter are read. Times are UTC.
"""
from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Any, Collection, NamedTuple, Sequence

from sqlalchemy import and_, case, func, or_, select

from undream.runlist import ACTIVE_STATUSES
from undream.store.jobs import IN_CHUNK, UNFINISHED
from undream.store.models import FrameJob, Run
from undream.store.snapshots import loads

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from sqlalchemy.orm import Session

class WorkerTally(NamedTuple):
    """One worker's jobs of one status in the window: how many finished in it, and its latest
    job start and finish (UTC; None if none)."""

    worker: str
    status: str
    finished: int
    last_started: dt.datetime | None
    last_finished: dt.datetime | None


class CurrentJob(NamedTuple):
    """A started job of an active run: who holds it and since when (UTC)."""

    worker: str
    run_id: str
    run: str
    phase: str
    k: int
    frame: int
    started: dt.datetime | None


class RunHealth(NamedTuple):
    """An active run's progress at its current iteration ``iteration`` (the jobs of that k only).

    ``unfinished``: jobs queued, started or retried; ``errored``: jobs whose last attempt failed and
    that have not succeeded since; ``last_job``: the latest job start or finish (UTC, None without
    jobs); ``farm``: the scheduling options fixed at submit (``max_attempts``, ``failure_budget``);
    ``owner``: the process driving the run itself (``undream run``), None on the farm.
    """

    id: str
    name: str
    status: str
    iteration: int
    updated: dt.datetime
    failures: int
    farm: dict[str, Any]
    owner: str | None
    unfinished: int
    errored: int
    last_job: dt.datetime | None
    started: int = 0  # of ``unfinished``, the jobs started (a worker holds them, or held them and died)


class JobError(NamedTuple):
    """The latest failed attempt of an active run's current iteration (its error unredacted)."""

    run_id: str
    phase: str
    k: int
    frame: int
    status: str
    attempts: int
    error: str


def _utc(stamp: dt.datetime | None) -> dt.datetime | None:
    """SQLite returns naive datetimes; every stored time is UTC."""
    return stamp if stamp is None or stamp.tzinfo is not None else stamp.replace(tzinfo=dt.timezone.utc)


def _latest(*stamps: dt.datetime | None) -> dt.datetime | None:
    present = [s for s in map(_utc, stamps) if s is not None]
    return max(present) if present else None


class ActivityTables:
    """The activity reads of :class:`undream.store.Store` (a mixin: needs ``_tx``)."""

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    def worker_activity(self, since: dt.datetime) -> tuple[list[WorkerTally], list[CurrentJob]]:
        """What the workers did since ``since`` (UTC), in two queries: per worker and job status,
        the jobs finished since then and the latest start and finish (jobs of runs active or
        updated since then, started or finished since then); and every started job of an active
        run, however old (a long job, or one whose worker is gone)."""
        fj, r = FrameJob.__table__, Run.__table__
        recent = or_(r.c.status.in_(ACTIVE_STATUSES), r.c.updated >= since)
        tallies = (select(fj.c.worker, fj.c.status,
                          func.sum(case((fj.c.finished >= since, 1), else_=0)),
                          func.max(fj.c.started), func.max(fj.c.finished))
                   .join(r, r.c.id == fj.c.run_id)
                   .where(recent, fj.c.worker.is_not(None), or_(fj.c.started >= since, fj.c.finished >= since))
                   .group_by(fj.c.worker, fj.c.status))
        current = (select(fj.c.worker, fj.c.run_id, r.c.name, fj.c.phase, fj.c.k, fj.c.frame, fj.c.started)
                   .join(r, r.c.id == fj.c.run_id)
                   .where(r.c.status.in_(ACTIVE_STATUSES), fj.c.status == "started", fj.c.worker.is_not(None))
                   .order_by(fj.c.worker, fj.c.started, fj.c.run_id, fj.c.frame))
        with self._tx("worker_activity", write=False) as s:
            rows = s.execute(tallies).all()
            held = s.execute(current).all()
        return ([WorkerTally(w, st, int(n or 0), _utc(a), _utc(b)) for w, st, n, a, b in rows],
                [CurrentJob(*row[:6], _utc(row[6])) for row in held])

    def active_farm_runs(self) -> int:
        """How many runs are queued, running or evaluating on the farm (not driven by their own
        process): the active runs less the owned ones, each counted down an index."""
        r = Run.__table__
        with self._tx("active_farm_runs", write=False) as s:
            active = s.scalar(select(func.count()).select_from(r).where(r.c.status.in_(ACTIVE_STATUSES))) or 0
            # by owner alone, so that the owner index serves it (the owned runs are few)
            owned = [status for (status,) in s.execute(select(r.c.status).where(r.c.owner > ""))]
        return active - sum(status in ACTIVE_STATUSES for status in owned)

    def _progress(self, s: "Session", run_ids: "Sequence[str] | None" = None) -> Any:
        """Per active run (or the runs ``run_ids``), its jobs at its current iteration: unfinished,
        errored, latest start and finish (a subquery)."""
        fj, r = FrameJob.__table__, Run.__table__
        errored = and_(fj.c.error.is_not(None), fj.c.status != "succeeded")
        query = (select(fj.c.run_id,
                        func.sum(case((fj.c.status.in_(UNFINISHED), 1), else_=0)).label("unfinished"),
                        func.sum(case((errored, 1), else_=0)).label("errored"),
                        func.sum(case((fj.c.status == "started", 1), else_=0)).label("started_jobs"),
                        func.max(fj.c.started).label("started"), func.max(fj.c.finished).label("finished"))
                 .join(r, r.c.id == fj.c.run_id).where(r.c.status.in_(ACTIVE_STATUSES), fj.c.k == r.c.iteration))
        if run_ids is not None:
            query = query.where(fj.c.run_id.in_(list(run_ids)))
        return query.group_by(fj.c.run_id).subquery()

    def stalled_runs(self, kinds: "Collection[str]", limit: int) -> tuple[dict[str, int], list[RunHealth]]:
        """The farm's active runs (not driven by their own process) by what they wait for: ``queued``
        (their start), ``jobs`` (their current iteration has jobs queued, started or retried) or
        ``callback`` (it has none: the phase's callback). Returns every kind's count and the runs of
        ``kinds``, at most ``limit``, those whose row changed longest ago first (an iteration's
        advance, a status change), with their current jobs' progress. Three queries, whatever the
        number of runs."""
        fj, r = FrameJob.__table__, Run.__table__
        pending = (select(fj.c.id).where(fj.c.run_id == r.c.id, fj.c.k == r.c.iteration,
                                         fj.c.status.in_(UNFINISHED)).exists())
        queued = r.c.status == "queued"
        of_kind = {"queued": queued, "jobs": and_(~queued, pending), "callback": and_(~queued, ~pending)}
        farm = and_(r.c.status.in_(ACTIVE_STATUSES), r.c.owner.is_(None))
        with self._tx("stalled_runs", write=False) as s:  # each run's EXISTS once: sums, not a GROUP BY
            n_queued, n_jobs, n_all = s.execute(select(func.sum(case((queued, 1), else_=0)),
                                                       func.sum(case((of_kind["jobs"], 1), else_=0)),
                                                       func.count()).where(farm)).one()
            counts = {"queued": int(n_queued or 0), "jobs": int(n_jobs or 0)}
            counts["callback"] = n_all - counts["queued"] - counts["jobs"]
            wanted = set(kinds)
            where = [] if wanted >= set(of_kind) else [or_(*(of_kind[k] for k in sorted(wanted)))]
            ids = [row[0] for row in s.execute(select(r.c.id).where(farm, *where)
                                               .order_by(r.c.updated, r.c.id).limit(limit))] if kinds else []
            rows = self._with_progress(s, ids)
        return counts, [_health(rows[run_id]) for run_id in ids]

    def _with_progress(self, s: "Session", run_ids: "Sequence[str]") -> dict[str, Any]:
        """The rows (id → row) of the runs ``run_ids`` with their current jobs' progress."""
        r, out = Run.__table__, {}
        for i in range(0, len(run_ids), IN_CHUNK):
            chunk = list(run_ids[i:i + IN_CHUNK])
            jobs = self._progress(s, chunk)
            query = (select(r.c.id, r.c.name, r.c.status, r.c.iteration, r.c.updated, r.c.failures, r.c.farm_json,
                            r.c.owner, jobs.c.unfinished, jobs.c.errored, jobs.c.started, jobs.c.finished,
                            jobs.c.started_jobs)
                     .outerjoin(jobs, jobs.c.run_id == r.c.id).where(r.c.id.in_(chunk)))
            out.update({row.id: row for row in s.execute(query)})
        return out

    def quiet_runs(self, before: dt.datetime, limit: int) -> list[RunHealth]:
        """The farm's active runs (not driven by their own process) in which nothing happened since
        ``before`` (UTC): the row unchanged, and no job of the current iteration started or finished
        since; at most ``limit``, quiet longest first, with their current jobs' progress. Two
        queries, whatever the number of runs (the stall rule of :mod:`scheduler.heal` decides which
        of them are stalled)."""
        fj, r = FrameJob.__table__, Run.__table__
        recent = (select(fj.c.id).where(fj.c.run_id == r.c.id, fj.c.k == r.c.iteration,
                                        or_(fj.c.started >= before, fj.c.finished >= before)).exists())
        query = (select(r.c.id).where(r.c.status.in_(ACTIVE_STATUSES), r.c.owner.is_(None), r.c.updated < before,
                                      ~recent).order_by(r.c.updated, r.c.id).limit(limit))
        with self._tx("quiet_runs", write=False) as s:
            ids = [row[0] for row in s.execute(query)]
            rows = self._with_progress(s, ids)
        return [_health(rows[run_id]) for run_id in ids]

    def failing_runs(self) -> list[tuple[RunHealth, JobError]]:
        """The active runs whose current iteration has a job whose last attempt failed and that has
        not succeeded since, each with the latest such attempt. Two queries, whatever the number of runs."""
        fj, r = FrameJob.__table__, Run.__table__
        errored = and_(fj.c.error.is_not(None), fj.c.status != "succeeded")
        newest = func.row_number().over(partition_by=fj.c.run_id,
                                        order_by=(func.coalesce(fj.c.finished, fj.c.started).desc(),
                                                  fj.c.id.desc()))
        # From the failed jobs (a partial index) to their runs, not from every active run to its jobs
        iteration = select(r.c.iteration).where(r.c.id == fj.c.run_id).scalar_subquery()
        failed = (select(fj.c.run_id, fj.c.phase, fj.c.k, fj.c.frame, fj.c.status, fj.c.attempts, fj.c.error,
                         newest.label("n"))
                  .where(errored, fj.c.run_id.in_(select(r.c.id).where(r.c.status.in_(ACTIVE_STATUSES))),
                         fj.c.k == iteration).subquery())
        with self._tx("failing_runs", write=False) as s:
            errors = {e.run_id: JobError(*e) for e in s.execute(select(*list(failed.c)[:-1]).where(failed.c.n == 1))}
            rows = self._with_progress(s, list(errors))
        return [(_health(rows[run_id]), error) for run_id, error in errors.items()]


def _health(row: Any) -> RunHealth:
    return RunHealth(row.id, row.name, row.status, row.iteration, _utc(row.updated),  # type: ignore[arg-type]
                     row.failures or 0, loads(row.farm_json) or {}, row.owner, int(row.unfinished or 0),
                     int(row.errored or 0), _latest(row.started, row.finished), int(row.started_jobs or 0))
