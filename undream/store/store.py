"""The run store: every read and write of an attack run's state, one short transaction each.

The farm's per-frame job and its reduce-and-step callback, the in-process
runner, the CLI and the dashboard touch run state only through :class:`Store`.
Rows live in the database (:mod:`undream.store.models`); arrays and attack
states live in blobs (:mod:`undream.store.blobs`) whose keys the rows hold.

Textures are H×W×3 float arrays of sRGB values in [0, 1]. Gradients are dL/dT
with the texture's shape (any float array is accepted; non-finite values are
kept, and the job's ``finite`` flag says so).

Concurrency: :meth:`Store.advance` is a compare-and-set on the run's iteration
number, so a callback that runs twice (or two callbacks racing) advances the run
exactly once. Job writes are upserts, so a redelivered job is recorded, not
duplicated.
"""
from __future__ import annotations

import uuid
from contextlib import contextmanager
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
from sqlalchemy import Engine, delete, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from undream.errors import StoreError
from undream.store.blobs import (
    BlobStore, attack_state_key, grad_key, run_prefix, texture_blob_key,
)
from undream.store.models import JOB_STATUSES, RUN_STATUSES, FrameJob, IterationRecord, Run, utcnow
from undream.store.snapshots import (
    FrameGrad, IterationSnapshot, JobSnapshot, RunSnapshot, dumps, finite_or_none,
)

WRITE_OPTION = "undream_begin"  # execution option: the BEGIN statement SQLite writers emit

TRANSITIONS: dict[str, tuple[str, ...]] = {
    "queued": ("running", "failed", "cancelled"),
    "running": ("evaluating", "done", "failed", "cancelled"),
    "evaluating": ("done", "failed", "cancelled"),
    "failed": ("queued",),      # resume
    "cancelled": ("queued",),   # resume
    "done": (),
}
RECORD_FIELDS = ("loss_mean", "n_ok", "n_bad", "dropped_frames", "grad_norm", "step_seconds",
                 "per_frame")
_MAX_SEED = 2**63 - 1
_JOB_KEY = ("run_id", "k", "frame")


def _int(field: str, value: Any, minimum: int, maximum: int = 2**31 - 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not minimum <= value <= maximum:
        raise StoreError(f"{field}: must be an integer in [{minimum}, {maximum}], got {value!r}")
    return int(value)


def _float(field: str, value: Any) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise StoreError(f"{field}: must be a number or None, got {value!r}")
    return finite_or_none(value)


def _texture(field: str, array: Any) -> np.ndarray:
    """Check an H×W×3 float sRGB texture in [0, 1]."""
    arr = np.asarray(array)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise StoreError(f"{field}: must be an H×W×3 texture, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise StoreError(f"{field}: must be a float array of sRGB values in [0, 1], "
                         f"got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)) or arr.min() < 0.0 or arr.max() > 1.0:
        raise StoreError(f"{field}: values must be finite sRGB in [0, 1], "
                         f"got range [{np.nanmin(arr)}, {np.nanmax(arr)}]")
    return arr


def _frames(value: Any) -> list[int]:
    if not isinstance(value, (list, tuple)):
        raise StoreError(f"record.dropped_frames: must be a list of frame indexes, got {value!r}")
    return [_int("record.dropped_frames", f, 0) for f in value]


def _record_values(record: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(record, Mapping):
        raise StoreError(f"record: must be a mapping of {', '.join(RECORD_FIELDS)}, got {record!r}")
    unknown = sorted(set(record) - set(RECORD_FIELDS))
    if unknown:
        raise StoreError(f"record: unknown field(s) {', '.join(map(str, unknown))}; "
                         f"valid fields are {', '.join(RECORD_FIELDS)}")
    return {
        "loss_mean": _float("record.loss_mean", record.get("loss_mean")),
        "n_ok": _int("record.n_ok", record.get("n_ok", 0), 0),
        "n_bad": _int("record.n_bad", record.get("n_bad", 0), 0),
        "grad_norm": _float("record.grad_norm", record.get("grad_norm")),
        "step_seconds": _float("record.step_seconds", record.get("step_seconds")),
        "dropped_json": dumps("record.dropped_frames", _frames(record.get("dropped_frames", []))),
        "per_frame_json": dumps("record.per_frame", record.get("per_frame", [])),
    }


class Store:
    """Run state in a SQL database plus a blob folder; see :func:`undream.store.open_store`."""

    def __init__(self, engine: Engine, blobs: BlobStore) -> None:
        self.engine = engine
        self.blobs = blobs
        self._writer = engine.execution_options(**{WRITE_OPTION: "BEGIN IMMEDIATE"})

    def __repr__(self) -> str:
        return f"Store({self.engine.url!r}, blobs={str(self.blobs.root)!r})"

    def close(self) -> None:
        """Close the database connections (the blobs need no closing)."""
        self.engine.dispose()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transactions --------------------------------------------------------

    @contextmanager
    def _tx(self, op: str, write: bool) -> Iterator[Session]:
        try:
            with Session(self._writer if write else self.engine) as session, session.begin():
                yield session
        except SQLAlchemyError as exc:
            reason = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]
            raise StoreError(f"{op}: database error at {self.engine.url!r}: {reason}") from exc

    @staticmethod
    def _run(session: Session, run_id: str) -> Run:
        row = session.get(Run, run_id) if isinstance(run_id, str) else None
        if row is None:
            raise StoreError(f"run {run_id!r}: not found")
        return row

    # -- runs ----------------------------------------------------------------

    def create_run(self, name: str, config: Mapping[str, Any], n_frames: int, seed: int,
                   texture0: np.ndarray, attack_state0: Mapping[str, Any] | None = None) -> str:
        """A new queued run at iteration 0 with starting texture ``texture0`` (H×W×3 sRGB, 0–1).

        ``config``: the run config as plain JSON data. ``attack_state0``: the attack's
        starting state as plain JSON (``state_to_dict``), or None for none. Returns the
        run id (a UUID string).
        """
        if not isinstance(name, str) or not name.strip() or len(name) > 200:
            raise StoreError(f"name: must be a non-empty string of at most 200 characters, "
                             f"got {name!r}")
        if not isinstance(config, Mapping):
            raise StoreError(f"config: must be a mapping, got {type(config).__name__}")
        values: dict[str, Any] = {
            "name": name, "config_json": dumps("config", dict(config)),
            "n_frames": _int("n_frames", n_frames, 1), "seed": _int("seed", seed, 0, _MAX_SEED)}
        texture = _texture("texture0", texture0)
        if attack_state0 is not None and not isinstance(attack_state0, Mapping):
            raise StoreError(f"attack_state0: must be a mapping (see state_to_dict) or None, "
                             f"got {type(attack_state0).__name__}")
        run_id = str(uuid.uuid4())
        try:
            self.blobs.put_array(texture_blob_key(run_id, 0), texture)
            if attack_state0 is not None:
                values["attack_state_ref"] = self.blobs.put_json(attack_state_key(run_id, 0),
                                                                 dict(attack_state0))
            with self._tx("create_run", write=True) as s:
                s.add(Run(id=run_id, status="queued", iteration=0, **values))
        except BaseException:
            self.blobs.delete_prefix(run_prefix(run_id))
            raise
        return run_id

    def get_run(self, run_id: str) -> RunSnapshot:
        with self._tx("get_run", write=False) as s:
            return RunSnapshot.of(self._run(s, run_id))

    def runs(self, status: str | None = None) -> list[RunSnapshot]:
        """Every run (or those with ``status``), oldest first."""
        query = select(Run).order_by(Run.created, Run.id)
        if status is not None:
            query = query.where(Run.status == self._check_status(status))
        with self._tx("runs", write=False) as s:
            return [RunSnapshot.of(r) for r in s.scalars(query)]

    @staticmethod
    def _check_status(status: Any) -> str:
        if status not in RUN_STATUSES:
            raise StoreError(f"status: {status!r} is not a run status; "
                             f"valid statuses are {', '.join(RUN_STATUSES)}")
        return status

    def set_status(self, run_id: str, status: str, error: str | None = None) -> None:
        """Move the run to ``status`` (see TRANSITIONS; same status again is a no-op
        that rewrites ``error``). ``error`` is stored as given: None clears it."""
        self._check_status(status)
        sources = [s for s, targets in TRANSITIONS.items() if status in targets] + [status]
        with self._tx("set_status", write=True) as s:
            result = s.execute(
                update(Run).where(Run.id == run_id, Run.status.in_(sources))
                .values(status=status, error=error)
                .execution_options(synchronize_session=False))
            if result.rowcount != 1:
                current = self._run(s, run_id).status
                allowed = ", ".join(TRANSITIONS[current]) or "nothing (final)"
                raise StoreError(f"run {run_id!r}: status transition {current} → {status} "
                                 f"is not allowed; from {current} it may go to {allowed}")

    def set_results(self, run_id: str, results: Mapping[str, Any]) -> None:
        """Store the run's evaluation results (plain JSON data)."""
        text = dumps("results", dict(results))
        with self._tx("set_results", write=True) as s:
            self._run(s, run_id).results_json = text

    def delete_run(self, run_id: str) -> None:
        """Delete the run, its jobs, its iteration records and all its blobs."""
        with self._tx("delete_run", write=True) as s:
            self._run(s, run_id)
            for table in (FrameJob, IterationRecord):
                s.execute(delete(table).where(table.run_id == run_id))
            s.execute(delete(Run).where(Run.id == run_id))
        self.blobs.delete_prefix(run_prefix(run_id))

    # -- textures and attack states ------------------------------------------

    def texture(self, run_id: str, k: int) -> np.ndarray:
        """Texture ``k`` of the run (H×W×3 sRGB, 0–1)."""
        key = texture_blob_key(run_id, _int("k", k, 0))
        if not self.blobs.exists(key):
            raise StoreError(f"run {run_id!r}: no texture for iteration {k} (blob {key!r} missing)")
        return self.blobs.get_array(key)

    def put_texture(self, run_id: str, k: int, texture: np.ndarray) -> None:
        """Store texture ``k`` (H×W×3 sRGB, 0–1) outside :meth:`advance` (e.g. evaluation)."""
        arr = _texture("texture", texture)
        key = texture_blob_key(run_id, _int("k", k, 0))
        self.get_run(run_id)
        self.blobs.put_array(key, arr)

    def attack_state(self, run_id: str, k: int) -> dict[str, Any] | None:
        """The attack state stored with texture ``k``; None when there is none (a run
        created without ``attack_state0``, at k = 0)."""
        key = attack_state_key(run_id, _int("k", k, 0))
        self.get_run(run_id)
        return self.blobs.get_json(key) if self.blobs.exists(key) else None

    def advance(self, run_id: str, k: int, texture_next: np.ndarray,
                attack_state: Mapping[str, Any], record: Mapping[str, Any]) -> bool:
        """Compare-and-set the run from iteration ``k`` to ``k+1``.

        In one transaction: ``iteration`` goes from ``k`` to ``k+1`` only if it is
        still ``k``; the winner writes texture ``k+1`` (H×W×3 sRGB, 0–1), the attack
        state for ``k+1`` (plain JSON, e.g. ``state_to_dict(state)``) and the
        :class:`IterationRecord` of step ``k`` (fields ``RECORD_FIELDS``) before it
        commits; if a blob write fails, nothing is committed.

        Returns True for the caller that advanced the run, False when the run is
        already past ``k`` (another caller won; nothing is written). StoreError when
        the run is behind ``k`` or missing.
        """
        k = _int("k", k, 0, 2**31 - 2)
        texture = _texture("texture_next", texture_next)
        if not isinstance(attack_state, Mapping):
            raise StoreError(f"attack_state: must be a mapping (see state_to_dict), "
                             f"got {type(attack_state).__name__}")
        values = _record_values(record)
        state_key = attack_state_key(run_id, k + 1)
        with self._tx("advance", write=True) as s:
            result = s.execute(
                update(Run).where(Run.id == run_id, Run.iteration == k)
                .values(iteration=k + 1, attack_state_ref=state_key)
                .execution_options(synchronize_session=False))
            if result.rowcount != 1:
                current = self._run(s, run_id).iteration
                if current > k:
                    return False
                raise StoreError(f"run {run_id!r}: cannot advance from iteration {k}; "
                                 f"the run is at iteration {current}")
            self.blobs.put_array(texture_blob_key(run_id, k + 1), texture)
            self.blobs.put_json(state_key, dict(attack_state))
            s.add(IterationRecord(run_id=run_id, k=k, **values))
        return True

    def iterations(self, run_id: str) -> list[IterationSnapshot]:
        """The run's iteration records, by ``k``."""
        with self._tx("iterations", write=False) as s:
            self._run(s, run_id)
            rows = s.scalars(select(IterationRecord).where(IterationRecord.run_id == run_id)
                             .order_by(IterationRecord.k))
            return [IterationSnapshot.of(r) for r in rows]

    # -- frame jobs ----------------------------------------------------------

    def _upsert_job(self, op: str, run_id: str, k: int, frame: int,
                    insert: dict[str, Any], conflict: dict[str, Any] | None) -> None:
        """Insert the job row with ``insert`` or, if it exists, update it with ``conflict``."""
        k = _int("k", k, 0)
        with self._tx(op, write=True) as s:
            n_frames = self._run(s, run_id).n_frames
            _int("frame", frame, 0, n_frames - 1)
            dialect = postgresql if s.get_bind().dialect.name == "postgresql" else sqlite
            stmt = dialect.insert(FrameJob.__table__).values(
                run_id=run_id, k=k, frame=int(frame), **insert)
            if conflict is None:
                stmt = stmt.on_conflict_do_nothing(index_elements=list(_JOB_KEY))
            else:
                stmt = stmt.on_conflict_do_update(index_elements=list(_JOB_KEY), set_=conflict)
            s.execute(stmt)

    def queue_jobs(self, run_id: str, k: int, frames: Sequence[int]) -> None:
        """Record frames ``frames`` of iteration ``k`` as queued (existing jobs are left alone)."""
        for frame in frames:
            self._upsert_job("queue_jobs", run_id, k, frame, {"status": "queued"}, None)

    def job_started(self, run_id: str, k: int, frame: int) -> None:
        """A worker starts the job: status started, one more attempt."""
        now = utcnow()
        self._upsert_job("job_started", run_id, k, frame,
                         {"status": "started", "attempts": 1, "started": now},
                         {"status": "started", "attempts": FrameJob.__table__.c.attempts + 1,
                          "started": now, "finished": None})

    def job_succeeded(self, run_id: str, k: int, frame: int, grad: np.ndarray, loss: float,
                      finite: bool, timings: Mapping[str, Any]) -> None:
        """Store the job's gradient dL/dT (a blob) and its loss, finiteness and timings (s)."""
        arr = np.asarray(grad)
        if not np.issubdtype(arr.dtype, np.floating):
            raise StoreError(f"grad: must be a float array, got dtype {arr.dtype}")
        if not isinstance(finite, (bool, np.bool_)):
            raise StoreError(f"finite: must be true or false, got {finite!r}")
        values = {"status": "succeeded", "loss": _float("loss", loss), "finite": bool(finite),
                  "timings_json": dumps("timings", dict(timings)), "error": None,
                  "finished": utcnow()}
        key = grad_key(run_id, _int("k", k, 0), _int("frame", frame, 0))
        self.get_run(run_id)
        values["grad_ref"] = self.blobs.put_array(key, arr)
        self._upsert_job("job_succeeded", run_id, k, frame, {**values, "attempts": 1}, values)

    def job_failed(self, run_id: str, k: int, frame: int, error: str,
                   will_retry: bool = False) -> None:
        """The job's attempt failed with ``error``; status retried if ``will_retry``, else failed."""
        values = {"status": "retried" if will_retry else "failed", "error": str(error),
                  "finished": utcnow()}
        self._upsert_job("job_failed", run_id, k, frame, {**values, "attempts": 1}, values)

    def jobs(self, run_id: str, k: int) -> list[JobSnapshot]:
        """The recorded jobs of iteration ``k``, by frame."""
        with self._tx("jobs", write=False) as s:
            self._run(s, run_id)
            rows = s.scalars(select(FrameJob).where(FrameJob.run_id == run_id, FrameJob.k == k)
                             .order_by(FrameJob.frame))
            return [JobSnapshot.of(r) for r in rows]

    def frame_grads(self, run_id: str, k: int) -> list[FrameGrad]:
        """Each recorded job of iteration ``k``, by frame: its gradient (None unless
        succeeded), loss (None if unknown or not finite) and finiteness flag."""
        out = []
        for job in self.jobs(run_id, k):
            ok = job.status == "succeeded" and job.grad_ref is not None
            grad = self.blobs.get_array(job.grad_ref) if ok else None  # type: ignore[arg-type]
            out.append(FrameGrad(job.frame, grad, job.loss, job.finite and ok))
        return out


__all__ = ["JOB_STATUSES", "RECORD_FIELDS", "RUN_STATUSES", "TRANSITIONS", "Store"]
