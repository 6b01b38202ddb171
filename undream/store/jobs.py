"""Per-frame jobs in the store: the attack's render-and-gradient jobs and the evaluation's jobs.

A job is keyed by (run, phase, k, frame): ``phase`` ``attack`` for iteration
``k``'s render-and-gradient job of frame ``frame`` (a position in the
sequence), ``pre`` / ``adversarial`` for the evaluation's render-and-predict
jobs. Writes are upserts, so a redelivered job is recorded, not duplicated;
``attempts`` counts every start.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Iterator, Mapping, Sequence

import numpy as np
from sqlalchemy import func, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from undream.errors import StoreError
from undream.store.blobs import BlobStore, eval_image_key, grad_key
from undream.store.checks import integer, number
from undream.store.models import JOB_PHASES, FrameJob, Run, utcnow
from undream.store.snapshots import FrameGrad, JobLine, JobSnapshot, dumps, loads_many

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

_JOB_KEY = ("run_id", "phase", "k", "frame")
UNFINISHED = ("queued", "started", "retried")  # a job in one of these has no result yet
IN_CHUNK = 500  # ids per ``IN (...)`` of a bulk read (old SQLite builds allow 999 parameters)


def _phase(phase: Any) -> str:
    if phase not in JOB_PHASES:
        raise StoreError(f"phase: {phase!r} is not a job phase; valid phases are {', '.join(JOB_PHASES)}")
    return phase


class JobTables:
    """The frame-job methods of :class:`undream.store.Store` (a mixin: needs ``_tx``, ``_run``, ``blobs``)."""

    blobs: BlobStore

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    @staticmethod
    def _run(session: Session, run_id: str) -> Run:  # pragma: no cover
        raise NotImplementedError

    def get_run(self, run_id: str) -> Any:  # pragma: no cover
        raise NotImplementedError

    def _upsert_job(self, op: str, run_id: str, k: int, frame: int, phase: str,
                    insert: dict[str, Any], conflict: dict[str, Any] | None) -> None:
        """Insert the job row with ``insert`` or, if it exists, update it with ``conflict``."""
        k = integer("k", k, 0)
        phase = _phase(phase)
        with self._tx(op, write=True) as s:
            n_frames = self._run(s, run_id).n_frames
            integer("frame", frame, 0, n_frames - 1)
            dialect = postgresql if s.get_bind().dialect.name == "postgresql" else sqlite
            stmt = dialect.insert(FrameJob.__table__).values(
                run_id=run_id, phase=phase, k=k, frame=int(frame), **insert)
            if conflict is None:
                stmt = stmt.on_conflict_do_nothing(index_elements=list(_JOB_KEY))
            else:
                stmt = stmt.on_conflict_do_update(index_elements=list(_JOB_KEY), set_=conflict)
            s.execute(stmt)

    def queue_jobs(self, run_id: str, k: int, frames: Sequence[int], phase: str = "attack") -> None:
        """Record frames ``frames`` of iteration ``k`` as queued (existing jobs are left alone)."""
        for frame in frames:
            self._upsert_job("queue_jobs", run_id, k, frame, phase, {"status": "queued"}, None)

    def job_started(self, run_id: str, k: int, frame: int, phase: str = "attack",
                    worker: str | None = None) -> None:
        """A worker (``host:pid``) starts the job: status started, one more attempt."""
        now = utcnow()
        self._upsert_job("job_started", run_id, k, frame, phase,
                         {"status": "started", "attempts": 1, "started": now, "worker": worker},
                         {"status": "started", "attempts": FrameJob.__table__.c.attempts + 1,
                          "started": now, "finished": None, "worker": worker})

    def job_succeeded(self, run_id: str, k: int, frame: int, grad: np.ndarray, loss: float,
                      finite: bool, timings: Mapping[str, Any],
                      result: Mapping[str, Any] | None = None) -> None:
        """Store an attack job's gradient dL/dT (a blob) and its loss, finiteness and timings (s);
        ``result``: small plain JSON kept with the job (the victim's prediction on the frame)."""
        arr = np.asarray(grad)
        if not np.issubdtype(arr.dtype, np.floating):
            raise StoreError(f"grad: must be a float array, got dtype {arr.dtype}")
        if not isinstance(finite, (bool, np.bool_)):
            raise StoreError(f"finite: must be true or false, got {finite!r}")
        values = {"status": "succeeded", "loss": number("loss", loss), "finite": bool(finite),
                  "timings_json": dumps("timings", dict(timings)), "error": None,
                  "result_json": None if result is None else dumps("result", dict(result)),
                  "finished": utcnow()}
        key = grad_key(run_id, integer("k", k, 0), integer("frame", frame, 0))
        self.get_run(run_id)
        values["grad_ref"] = self.blobs.put_array(key, arr)
        self._upsert_job("job_succeeded", run_id, k, frame, "attack", {**values, "attempts": 1}, values)

    def eval_succeeded(self, run_id: str, k: int, frame: int, phase: str, result: Mapping[str, Any],
                       image: np.ndarray, timings: Mapping[str, Any]) -> None:
        """Store an evaluation job's result (plain JSON: prediction, loss), its frame and timings."""
        if _phase(phase) == "attack":
            raise StoreError("phase: evaluation results belong to phase 'pre' or 'adversarial'")
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise StoreError(f"image: must be an H×W×3 uint8 sRGB frame, got {img.dtype} {img.shape}")
        values = {"status": "succeeded", "result_json": dumps("result", dict(result)),
                  "timings_json": dumps("timings", dict(timings)), "error": None, "finished": utcnow(),
                  "finite": True}
        self.get_run(run_id)
        values["image_ref"] = self.blobs.put_array(
            eval_image_key(run_id, phase, integer("frame", frame, 0)), img)
        self._upsert_job("eval_succeeded", run_id, k, frame, phase, {**values, "attempts": 1}, values)

    def job_failed(self, run_id: str, k: int, frame: int, error: str, will_retry: bool = False,
                   phase: str = "attack") -> None:
        """The job's attempt failed with ``error``; status retried if ``will_retry``, else failed."""
        values = {"status": "retried" if will_retry else "failed", "error": str(error),
                  "finished": utcnow()}
        self._upsert_job("job_failed", run_id, k, frame, phase, {**values, "attempts": 1}, values)

    def jobs(self, run_id: str, k: int | None = None, phase: str = "attack") -> list[JobSnapshot]:
        """The recorded jobs of ``phase`` (of iteration ``k``, or all), by k and frame.

        Read as plain rows, not ORM objects, their JSON decoded at once (a run's thousands of
        jobs in a third of the time).
        """
        table = FrameJob.__table__
        query = select(table).where(table.c.run_id == run_id, table.c.phase == _phase(phase))
        if k is not None:
            query = query.where(table.c.k == k)
        with self._tx("jobs", write=False) as s:
            self._run(s, run_id)
            return JobSnapshot.many(s.execute(query.order_by(table.c.k, table.c.frame)).all())

    def job_lines(self, run_id: str, phase: str = "attack") -> list[JobLine]:
        """Every recorded job of ``phase``, by k and frame, as :class:`JobLine` (the columns a
        display needs: a 6400-job run in a third of :meth:`jobs`' time)."""
        table = FrameJob.__table__
        cols = (table.c.k, table.c.frame, table.c.status, table.c.attempts, table.c.worker, table.c.error,
                table.c.timings_json, table.c.result_json)
        query = (select(*cols).where(table.c.run_id == run_id, table.c.phase == _phase(phase))
                 .order_by(table.c.k, table.c.frame))
        with self._tx("job_lines", write=False) as s:
            self._run(s, run_id)
            rows = s.execute(query).all()
        timings, results = loads_many([r[6] for r in rows]), loads_many([r[7] for r in rows])
        return [JobLine(*r[:6], t or {}, res) for r, t, res in zip(rows, timings, results)]

    def job_counts(self, run_ids: Sequence[str]) -> dict[tuple[str, str, int], dict[str, int]]:
        """(run id, phase, k) → status → number of jobs, for the runs ``run_ids`` (a list page's
        progress), in one grouped query per :data:`IN_CHUNK` runs."""
        table = FrameJob.__table__
        ids, out = list(dict.fromkeys(run_ids)), {}
        with self._tx("job_counts", write=False) as s:
            for i in range(0, len(ids), IN_CHUNK):
                query = (select(table.c.run_id, table.c.phase, table.c.k, table.c.status, func.count())
                         .where(table.c.run_id.in_(ids[i:i + IN_CHUNK]))
                         .group_by(table.c.run_id, table.c.phase, table.c.k, table.c.status))
                for run_id, phase, k, status, n in s.execute(query):
                    out.setdefault((run_id, phase, k), {})[status] = n
        return out

    def requeue_failed(self, run_id: str, k: int, frames: Sequence[int],
                       phase: str = "attack") -> tuple[int, int]:
        """Count failed jobs ``frames`` against the run's failure budget and queue them again.

        In one transaction: the jobs that are still ``failed`` go back to
        ``queued`` with no attempts, and the run's ``failures`` grows by their
        number. Returns (jobs requeued, the run's failures now); a second caller
        for the same jobs requeues nothing.
        """
        frames = [integer("frame", f, 0) for f in frames]
        with self._tx("requeue_failed", write=True) as s:
            self._run(s, run_id)
            n = s.execute(
                update(FrameJob).where(FrameJob.run_id == run_id, FrameJob.phase == _phase(phase),
                                       FrameJob.k == k, FrameJob.frame.in_(frames),
                                       FrameJob.status == "failed")
                .values(status="queued", attempts=0).execution_options(synchronize_session=False)
            ).rowcount
            s.execute(update(Run).where(Run.id == run_id).values(failures=Run.failures + n)
                      .execution_options(synchronize_session=False))
            return n, s.scalar(select(Run.failures).where(Run.id == run_id))

    def reset_jobs(self, run_id: str, k: int, frames: Sequence[int], phase: str = "attack") -> int:
        """Queue jobs ``frames`` again with no attempts, unless they succeeded (resume); returns how many."""
        frames = [integer("frame", f, 0) for f in frames]
        with self._tx("reset_jobs", write=True) as s:
            self._run(s, run_id)
            return s.execute(
                update(FrameJob).where(FrameJob.run_id == run_id, FrameJob.phase == _phase(phase),
                                       FrameJob.k == k, FrameJob.frame.in_(frames),
                                       FrameJob.status != "succeeded")
                .values(status="queued", attempts=0).execution_options(synchronize_session=False)
            ).rowcount

    def reset_failures(self, run_id: str) -> None:
        """Give the run a fresh failure budget (resume)."""
        with self._tx("reset_failures", write=True) as s:
            self._run(s, run_id).failures = 0

    def frame_grads(self, run_id: str, k: int) -> list[FrameGrad]:
        """Each recorded attack job of iteration ``k``, by frame: its gradient (None unless
        succeeded), loss (None if unknown or not finite) and finiteness flag."""
        return list(self._grads(self.jobs(run_id, k)))

    def _grads(self, jobs: list[JobSnapshot]) -> Iterator[FrameGrad]:
        for job in jobs:
            ok = job.status == "succeeded" and job.grad_ref is not None
            grad = self.blobs.get_array(job.grad_ref) if ok else None  # type: ignore[arg-type]
            yield FrameGrad(job.frame, grad, job.loss, job.finite and ok)
