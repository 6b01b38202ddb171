"""Per-frame jobs in the store: the attack's render-and-gradient jobs and the evaluation's jobs.

A job is keyed by (run, phase, k, frame): ``phase`` ``attack`` for iteration
``k``'s render-and-gradient job of frame ``frame`` (a position in the
sequence), ``pre`` / ``adversarial`` for the evaluation's render-and-predict
jobs. Writes are upserts, so a redelivered job is recorded, not duplicated;
``attempts`` counts every start.

A batch of frames (``queue_jobs``, ``jobs_started``, ``jobs_succeeded``,
``evals_succeeded``) is written in one transaction by one executemany
``INSERT … ON CONFLICT``, after every item is checked; the one-frame methods are
batches of one.
"""
from __future__ import annotations

import datetime as dt
import functools
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Mapping, Sequence

import numpy as np
from sqlalchemy import func, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from undream.errors import StoreError
from undream.store.blobs import BlobStore, eval_image_key, grad_key
from undream.store.checks import integer, number
from undream.store.models import JOB_PHASES, FrameJob, Run, utcnow
from undream.store.snapshots import FrameGrad, JobLine, JobSnapshot, RunSnapshot, dumps, loads_many

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

_JOB_KEY = ("run_id", "phase", "k", "frame")
UNFINISHED = ("queued", "started", "retried")  # a job in one of these has no result yet
IN_CHUNK = 500  # ids per ``IN (...)`` of a bulk read (old SQLite builds allow 999 parameters)


def _phase(phase: Any) -> str:
    if phase not in JOB_PHASES:
        raise StoreError(f"phase: {phase!r} is not a job phase; valid phases are {', '.join(JOB_PHASES)}")
    return phase


@dataclass(frozen=True)
class JobResult:
    """An attack job's outcome, one item of :meth:`JobTables.jobs_succeeded`.

    ``frame``: the frame's position in the sequence; ``grad``: dL/dT, a float
    array with the texture's shape (H×W×3 for an sRGB 0–1 texture; non-finite
    values are kept); ``loss``: the frame's loss (None or non-finite: unknown);
    ``finite``: whether loss and gradient are finite; ``timings``: seconds per
    stage (plain JSON); ``result``: small plain JSON kept with the job (the
    victim's prediction on the frame), or None.
    """

    frame: int
    grad: np.ndarray
    loss: float | None
    finite: bool
    timings: Mapping[str, Any]
    result: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class EvalResult:
    """An evaluation job's outcome, one item of :meth:`JobTables.evals_succeeded`: frame
    ``frame``'s ``result`` (plain JSON: prediction, loss), its rendered ``image`` (H×W×3 uint8
    sRGB, 0–255) and ``timings`` (seconds per stage)."""

    frame: int
    result: Mapping[str, Any]
    image: np.ndarray
    timings: Mapping[str, Any]


def _row(run_id: str, phase: str, k: int, frame: int, values: Mapping[str, Any]) -> dict[str, Any]:
    return {"run_id": run_id, "phase": phase, "k": k, "frame": frame, **values}


def _attack_values(item: Any, now: dt.datetime) -> dict[str, Any]:
    """The columns of a succeeded attack job but its gradient key (known once the blob is written)."""
    if not isinstance(item, JobResult):
        raise StoreError(f"results: each item must be a JobResult, got {type(item).__name__}")
    dtype = np.asarray(item.grad).dtype
    if not np.issubdtype(dtype, np.floating):
        raise StoreError(f"grad: must be a float array, got dtype {dtype} (frame {item.frame!r})")
    if not isinstance(item.finite, (bool, np.bool_)):
        raise StoreError(f"finite: must be true or false, got {item.finite!r} (frame {item.frame!r})")
    return {"status": "succeeded", "loss": number("loss", item.loss), "finite": bool(item.finite),
            "timings_json": dumps("timings", dict(item.timings)), "error": None,
            "result_json": None if item.result is None else dumps("result", dict(item.result)),
            "finished": now}


def _eval_values(item: Any, now: dt.datetime) -> dict[str, Any]:
    """The columns of a succeeded evaluation job but its image key (known once the blob is written)."""
    if not isinstance(item, EvalResult):
        raise StoreError(f"results: each item must be an EvalResult, got {type(item).__name__}")
    img = np.asarray(item.image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise StoreError(f"image: must be an H×W×3 uint8 sRGB frame, got {img.dtype} {img.shape} "
                         f"(frame {item.frame!r})")
    return {"status": "succeeded", "result_json": dumps("result", dict(item.result)),
            "timings_json": dumps("timings", dict(item.timings)), "error": None, "finished": now,
            "finite": True}


def _checked_frames(n_frames: int, frames: Iterable[Any], unique: bool = True) -> list[int]:
    """``frames``, each an integer in [0, n_frames - 1] and, if ``unique``, given once (a batch
    records each job once); StoreError naming the first bad one."""
    checked = [integer("frame", f, 0, n_frames - 1) for f in frames]
    twice = [f for f, n in Counter(checked).items() if n > 1] if unique else []
    if twice:
        raise StoreError(f"frames: frame {twice[0]} is given more than once; a batch records "
                         "each frame once")
    return checked


@functools.lru_cache(maxsize=32)
def _upsert(dialect_name: str, update: tuple[str, ...] | None, attempt: bool) -> Any:
    """The ``INSERT … ON CONFLICT`` statement of :meth:`JobTables._upsert_jobs`, built once per
    shape (building one costs more than a job's row write: measured 0.6 ms of SQLAlchemy's column
    bookkeeping each time)."""
    dialect = postgresql if dialect_name == "postgresql" else sqlite
    stmt = dialect.insert(FrameJob.__table__)
    if update is None:
        return stmt.on_conflict_do_nothing(index_elements=list(_JOB_KEY))
    set_: dict[str, Any] = {c: stmt.excluded[c] for c in update}
    if attempt:
        set_["attempts"] = FrameJob.__table__.c.attempts + 1
    return stmt.on_conflict_do_update(index_elements=list(_JOB_KEY), set_=set_)


class JobTables:
    """The frame-job methods of :class:`undream.store.Store` (a mixin: needs ``_tx``, ``_run``, ``blobs``)."""

    blobs: BlobStore

    def _tx(self, op: str, write: bool) -> "AbstractContextManager[Session]":  # pragma: no cover
        raise NotImplementedError

    @staticmethod
    def _run(session: Session, run_id: str) -> Run:  # pragma: no cover
        raise NotImplementedError

    @staticmethod
    def _run_snapshot(session: Session, run_id: str) -> RunSnapshot:  # pragma: no cover
        raise NotImplementedError

    _frame_counts: dict[str, int]  # run id → its number of frames, once read (it never changes)

    def _n_frames(self, s: Session, run_id: str) -> int:
        """The run's number of frames, the one column a job write needs; StoreError if no such run.
        Read once per run and process: a job write for a run deleted since is refused by the
        database's foreign key instead."""
        n = self._frame_counts.get(run_id) if isinstance(run_id, str) else None
        if n is None:
            n = s.scalar(select(Run.n_frames).where(Run.id == run_id)) if isinstance(run_id, str) else None
            if n is None:
                raise StoreError(f"run {run_id!r}: not found")
            self._frame_counts[run_id] = n
        return n

    def _frames(self, s: Session, run_id: str, frames: Iterable[Any], unique: bool = True) -> list[int]:
        """``frames`` checked against the run (:func:`_checked_frames`)."""
        return _checked_frames(self._n_frames(s, run_id), frames, unique)

    def _batch_frames(self, op: str, run_id: str, frames: Iterable[Any]) -> list[int]:
        """:meth:`_frames` before any blob is written (in a read transaction of its own the first
        time this process meets the run)."""
        known = self._frame_counts.get(run_id) if isinstance(run_id, str) else None
        if known is not None:
            return _checked_frames(known, frames)
        with self._tx(op, write=False) as s:
            return self._frames(s, run_id, frames)

    @staticmethod
    def _upsert_jobs(s: Session, rows: list[dict[str, Any]], update: Sequence[str] | None,
                     attempt: bool = False) -> None:
        """Insert the job rows ``rows`` (the same columns each) in one executemany
        ``INSERT … ON CONFLICT``: an existing job is left alone (``update`` None), or takes the
        new row's columns ``update`` and, if ``attempt``, counts one more attempt."""
        if rows:
            s.execute(_upsert(s.get_bind().dialect.name, None if update is None else tuple(update), attempt), rows)

    def queue_jobs(self, run_id: str, k: int, frames: Iterable[int], phase: str = "attack") -> None:
        """Record frames ``frames`` of iteration ``k`` as queued (existing jobs are left alone),
        in one transaction and one statement."""
        k, phase = integer("k", k, 0), _phase(phase)
        with self._tx("queue_jobs", write=True) as s:
            checked = dict.fromkeys(self._frames(s, run_id, frames, unique=False))
            self._upsert_jobs(s, [_row(run_id, phase, k, f, {"status": "queued"}) for f in checked], None)

    def claim_jobs(self, run_id: str, k: int, frames: Iterable[int], phase: str,
                   statuses: Sequence[str]) -> bool:
        """Record frames ``frames`` of ``phase`` at ``k`` as queued, if the run is still at iteration
        ``k`` in one of ``statuses`` and has no job of ``phase`` at ``k`` yet: True for the one caller
        that recorded them (it dispatches them), False with nothing written otherwise. The run's row
        is locked first (PostgreSQL; SQLite writers are serialised), so two callers racing to plan
        the same phase cannot both win."""
        k, phase = integer("k", k, 0), _phase(phase)
        table = FrameJob.__table__
        with self._tx("claim_jobs", write=True) as s:
            run = s.execute(select(Run.status, Run.iteration).where(Run.id == run_id).with_for_update()).first()
            if run is None:
                raise StoreError(f"run {run_id!r}: not found")
            if run.status not in statuses or run.iteration != k:
                return False
            if s.scalar(select(table.c.id).where(table.c.run_id == run_id, table.c.phase == phase,
                                                 table.c.k == k).limit(1)) is not None:
                return False
            checked = dict.fromkeys(self._frames(s, run_id, frames, unique=False))
            self._upsert_jobs(s, [_row(run_id, phase, k, f, {"status": "queued"}) for f in checked], None)
            return True

    def jobs_started(self, run_id: str, k: int, frames: Iterable[int], phase: str = "attack",
                     worker: str | None = None) -> None:
        """A worker (``host:pid``) starts the jobs ``frames`` of iteration ``k``: each gets status
        started and one more attempt, in one transaction; a bad frame writes nothing."""
        k, phase = integer("k", k, 0), _phase(phase)
        values = {"status": "started", "attempts": 1, "started": utcnow(), "finished": None,
                  "worker": worker}
        with self._tx("jobs_started", write=True) as s:
            rows = [_row(run_id, phase, k, f, values) for f in self._frames(s, run_id, frames)]
            self._upsert_jobs(s, rows, ("status", "started", "finished", "worker"), attempt=True)

    def job_started(self, run_id: str, k: int, frame: int, phase: str = "attack",
                    worker: str | None = None) -> None:
        """A worker (``host:pid``) starts the job: status started, one more attempt."""
        self.jobs_started(run_id, k, [frame], phase, worker)

    def jobs_succeeded(self, run_id: str, k: int, results: Iterable[JobResult]) -> None:
        """Store attack jobs' outcomes (:class:`JobResult`): each gradient dL/dT as a blob, then
        every job's row (status succeeded, loss, finiteness, timings, result) in one transaction.
        The gradients are written without waiting for the disk (``durable=False``): they live
        for one iteration, and a job whose gradient a power cut lost is run again
        (:meth:`lost_gradients`, :func:`scheduler.stages.resume`).

        Every item is checked first: a bad frame, dtype or value is a StoreError naming the
        field, and nothing (blob or row) is written.
        """
        k, items, now = integer("k", k, 0), list(results), utcnow()
        rows = [_attack_values(item, now) for item in items]
        frames = self._batch_frames("jobs_succeeded", run_id, [item.frame for item in items])
        for row, frame, item in zip(rows, frames, items):  # not fsynced: a gradient lost is computed again
            row["grad_ref"] = self.blobs.put_array(grad_key(run_id, k, frame), np.asarray(item.grad), durable=False)
        self._write_results("jobs_succeeded", run_id, k, "attack", frames, rows)

    def job_succeeded(self, run_id: str, k: int, frame: int, grad: np.ndarray, loss: float,
                      finite: bool, timings: Mapping[str, Any],
                      result: Mapping[str, Any] | None = None) -> None:
        """Store an attack job's gradient dL/dT (a blob) and its loss, finiteness and timings (s);
        ``result``: small plain JSON kept with the job (the victim's prediction on the frame)."""
        self.jobs_succeeded(run_id, k, [JobResult(frame, grad, loss, finite, timings, result)])

    def evals_succeeded(self, run_id: str, k: int, phase: str, results: Iterable[EvalResult]) -> None:
        """Store evaluation jobs' outcomes (:class:`EvalResult`): each frame as a blob, then every
        job's row (result JSON, timings) in one transaction; checked first like :meth:`jobs_succeeded`."""
        k = integer("k", k, 0)
        if _phase(phase) == "attack":
            raise StoreError("phase: evaluation results belong to phase 'pre' or 'adversarial'")
        items, now = list(results), utcnow()
        rows = [_eval_values(item, now) for item in items]
        frames = self._batch_frames("evals_succeeded", run_id, [item.frame for item in items])
        for row, frame, item in zip(rows, frames, items):
            row["image_ref"] = self.blobs.put_array(eval_image_key(run_id, phase, frame), item.image)
        self._write_results("evals_succeeded", run_id, k, phase, frames, rows)

    def eval_succeeded(self, run_id: str, k: int, frame: int, phase: str, result: Mapping[str, Any],
                       image: np.ndarray, timings: Mapping[str, Any]) -> None:
        """Store an evaluation job's result (plain JSON: prediction, loss), its frame and timings."""
        self.evals_succeeded(run_id, k, phase, [EvalResult(frame, result, image, timings)])

    def _write_results(self, op: str, run_id: str, k: int, phase: str, frames: list[int],
                       rows: list[dict[str, Any]]) -> None:
        """Upsert finished jobs' rows (a new job counts one attempt) in one transaction."""
        if not rows:
            return
        with self._tx(op, write=True) as s:
            new = [_row(run_id, phase, k, f, {**r, "attempts": 1}) for f, r in zip(frames, rows)]
            self._upsert_jobs(s, new, tuple(rows[0]))

    def job_failed(self, run_id: str, k: int, frame: int, error: str, will_retry: bool = False,
                   phase: str = "attack") -> None:
        """The job's attempt failed with ``error``; status retried if ``will_retry``, else failed."""
        k, phase = integer("k", k, 0), _phase(phase)
        values = {"status": "retried" if will_retry else "failed", "error": str(error),
                  "finished": utcnow()}
        with self._tx("job_failed", write=True) as s:
            (frame,) = self._frames(s, run_id, [frame])
            self._upsert_jobs(s, [_row(run_id, phase, k, frame, {**values, "attempts": 1})], tuple(values))

    def jobs(self, run_id: str, k: int | None = None, phase: str = "attack",
             frames: Sequence[int] | None = None) -> list[JobSnapshot]:
        """The recorded jobs of ``phase`` (of iteration ``k``, or all; of ``frames``, or all), by k
        and frame.

        Read as plain rows, not ORM objects, their JSON decoded at once (a run's thousands of
        jobs in a third of the time).
        """
        with self._tx("jobs", write=False) as s:
            self._n_frames(s, run_id)  # the run exists
            return self._read_jobs(s, run_id, k, phase, frames)

    def batch_view(self, run_id: str, k: int, phase: str, frames: Sequence[int]) -> tuple[RunSnapshot, list[JobSnapshot]]:
        """The run and its jobs ``frames`` of ``phase`` at ``k``, in one transaction: what a batch
        task reads before it works (:func:`scheduler.stages.run_batch`)."""
        with self._tx("batch_view", write=False) as s:
            return self._run_snapshot(s, run_id), self._read_jobs(s, run_id, k, phase, frames)

    @staticmethod
    def _read_jobs(s: Session, run_id: str, k: int | None, phase: str,
                   frames: Sequence[int] | None) -> list[JobSnapshot]:
        table = FrameJob.__table__
        query = select(table).where(table.c.run_id == run_id, table.c.phase == _phase(phase))
        if k is not None:
            query = query.where(table.c.k == k)
        if frames is not None and len(frames) <= IN_CHUNK:  # a longer list: every frame's row, filtered here
            query = query.where(table.c.frame.in_([integer("frame", f, 0) for f in frames]))
        jobs = JobSnapshot.many(s.execute(query.order_by(table.c.k, table.c.frame)).all())
        if frames is not None and len(frames) > IN_CHUNK:
            wanted = set(frames)
            jobs = [j for j in jobs if j.frame in wanted]
        return jobs

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

    def reset_jobs(self, run_id: str, k: int, frames: Sequence[int], phase: str = "attack",
                   succeeded: bool = False, keep_attempts: bool = False) -> int:
        """Queue jobs ``frames`` again with no attempts (``keep_attempts``: with those they used),
        unless they succeeded (resume; ``succeeded``: those too, their result forgotten); returns how many."""
        frames = [integer("frame", f, 0) for f in frames]
        with self._tx("reset_jobs", write=True) as s:
            self._run(s, run_id)
            which = [FrameJob.run_id == run_id, FrameJob.phase == _phase(phase), FrameJob.k == k,
                     FrameJob.frame.in_(frames)]
            if not succeeded:
                which.append(FrameJob.status != "succeeded")
            values: dict[str, Any] = {"status": "queued"} if keep_attempts else {"status": "queued", "attempts": 0}
            if succeeded:
                values["grad_ref"] = None
            return s.execute(update(FrameJob).where(*which).values(**values)
                             .execution_options(synchronize_session=False)).rowcount

    def lost_gradients(self, run_id: str, k: int) -> list[int]:
        """The frames of iteration ``k`` whose job succeeded but whose gradient blob is gone or
        unreadable (written without fsync, :meth:`jobs_succeeded`, and lost with the machine's power)."""
        lost = []
        for job in self.jobs(run_id, k):
            if job.status == "succeeded" and job.grad_ref is not None:
                try:
                    self.blobs.get_array(job.grad_ref)
                except StoreError:
                    lost.append(job.frame)
        return lost

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
