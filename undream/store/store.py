"""The run store: every read and write of an attack run's state, one short transaction each.

The farm's per-frame job and its reduce-and-step callback, the in-process
runner, the CLI and the dashboard touch run state only through :class:`Store`
(frame jobs: :mod:`undream.store.jobs`; run leases: :mod:`undream.store.leases`).
Rows live in the database (:mod:`undream.store.models`); arrays and attack
states live in blobs (:mod:`undream.store.blobs`) whose keys the rows hold.

Textures are H×W×3 float arrays of sRGB values in [0, 1]. Gradients are dL/dT
with the texture's shape (any float array is accepted; non-finite values are
kept, and the job's ``finite`` flag says so).

Concurrency: :meth:`Store.advance` is a compare-and-set on the run's iteration
number (and on the run still being active), so a callback that runs twice (or
two callbacks racing) advances the run exactly once, and a cancelled run never
advances. Job writes are upserts, so a redelivered job is recorded, not
duplicated (:mod:`undream.store.jobs`).

Attack states: the JSON keeps scalars; arrays (T0, the visibility mask,
APGD's best point, ...) are content-addressed ``.npy`` blobs that the JSON
names as ``{"array": key}``, so an array that does not change between
iterations is written once.
"""
from __future__ import annotations

import datetime as dt
import uuid
from contextlib import contextmanager
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
from sqlalchemy import Engine, delete, insert, select, update
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from undream import interrupts
from undream.errors import StoreError
from undream.store.activity import ActivityTables
from undream.store.events import EventMethods
from undream.store.blobs import (
    BlobStore, array_digest, array_key, attack_state_key, final_texture_key, grad_prefix, run_prefix, seen_key,
    texture_blob_key,
)
from undream.store.checks import RECORD_FIELDS, integer, mapping, record_values, texture
from undream.store.jobs import IN_CHUNK, JobTables
from undream.store.leases import LeaseMethods
from undream.store.models import JOB_STATUSES, RUN_STATUSES, FrameJob, IterationRecord, Run, Sweep, utcnow
from undream.store.newrun import NewRun, check_name, run_row
from undream.store.pages import ListMethods
from undream.store.snapshots import IterationSnapshot, RunSnapshot, SweepSnapshot, dumps

WRITE_OPTION = "undream_begin"  # execution option: the BEGIN statement SQLite writers emit

TRANSITIONS: dict[str, tuple[str, ...]] = {
    "queued": ("running", "failed", "cancelled"),
    "running": ("evaluating", "done", "failed", "cancelled"),
    "evaluating": ("done", "failed", "cancelled"),
    "failed": ("queued",),      # resume
    "cancelled": ("queued",),   # resume
    "done": (),
}
ACTIVE = ("queued", "running")  # statuses in which a run may advance


def db_reason(exc: SQLAlchemyError) -> str:
    """The first line of a database error's own message (the driver's, inside SQLAlchemy's wrapper)."""
    return str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]


def _state_doc(blobs: BlobStore, run_id: str, field: str, state: Any,
               arrays: Mapping[str, np.ndarray] | None) -> dict[str, Any]:
    """The JSON document of an attack state: ``state``'s scalars, ``arrays`` as blob references."""
    doc = dict(mapping(field, state, " (see state_to_dict)"))
    for name, value in (arrays or {}).items():
        if name in doc:
            raise StoreError(f"{field}: {name!r} is given both as a scalar and as an array")
        arr = np.asarray(value)
        if arr.dtype.hasobject:
            raise StoreError(f"{field}.{name}: must be a numeric array, got dtype {arr.dtype}")
        key = array_key(run_id, array_digest(arr))
        if not blobs.exists(key):
            blobs.put_array(key, arr)
        doc[name] = {"array": key}
    return doc


class Store(JobTables, LeaseMethods, ListMethods, ActivityTables, EventMethods):
    """Run state in a SQL database plus a blob folder; see :func:`undream.store.open_store`."""

    def __init__(self, engine: Engine, blobs: BlobStore) -> None:
        self.engine = engine
        self.blobs = blobs
        self._writer = engine.execution_options(**{WRITE_OPTION: "BEGIN IMMEDIATE"})
        self._frame_counts: dict[str, int] = {}

    def __repr__(self) -> str:
        url = self.engine.url.render_as_string(hide_password=True)
        return f"Store({url!r}, blobs={self.blobs.where!r})"

    def close(self) -> None:
        """Close the database connections, the blob backend's, and this process's blob copies."""
        self.blobs.close()
        self.engine.dispose()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transactions --------------------------------------------------------

    @contextmanager
    def _tx(self, op: str, write: bool) -> Iterator[Session]:
        try:  # a signal during the transaction ends the command after it (undream.interrupts)
            with interrupts.held(), Session(self._writer if write else self.engine) as session, session.begin():
                if not write:
                    yield session
                    return
                with self.blobs.joined(session.connection()):  # blobs in the database: one transaction
                    yield session
        except SQLAlchemyError as exc:
            reason = db_reason(exc)
            url = self.engine.url.render_as_string(hide_password=True)
            raise StoreError(f"{op}: database error at {url!r}: {reason}") from exc

    @staticmethod
    def _run_snapshot(session: Session, run_id: str) -> RunSnapshot:
        """The run read as a plain row (every job reads its run, so no ORM object); StoreError if none."""
        table = Run.__table__
        row = session.execute(select(table).where(table.c.id == run_id)).first() if isinstance(run_id, str) else None
        if row is None:
            raise StoreError(f"run {run_id!r}: not found")
        return RunSnapshot.of(row)  # type: ignore[arg-type]

    @staticmethod
    def _run(session: Session, run_id: str) -> Run:
        row = session.get(Run, run_id) if isinstance(run_id, str) else None
        if row is None:
            raise StoreError(f"run {run_id!r}: not found")
        return row

    # -- runs ----------------------------------------------------------------

    def create_run(self, name: str, config: Mapping[str, Any], n_frames: int, seed: int,
                   texture0: np.ndarray | None = None, attack_state0: Mapping[str, Any] | None = None,
                   *, arrays0: Mapping[str, np.ndarray] | None = None, scene_ref: str | None = None,
                   out_dir: str | None = None, sweep_id: str | None = None,
                   farm: Mapping[str, Any] | None = None) -> str:
        """A new queued run at iteration 0; returns its id (a UUID string).

        ``config``: the run config as plain JSON data. ``texture0`` (H×W×3 sRGB,
        0–1) and ``attack_state0`` (plain JSON, ``arrays0`` its arrays) may be
        given now or later with :meth:`start_run` (the farm computes them on a
        worker). ``scene_ref``: blob key of the packed scene; ``out_dir``: where
        the run's outputs go; ``sweep_id``: the sweep it belongs to; ``farm``:
        its scheduling options (plain JSON). Recorded as :meth:`create_runs` records one.
        """
        run = NewRun(name, config, n_frames, seed, scene_ref=scene_ref, out_dir=out_dir, farm=farm)
        row = run_row(run, sweep_id, utcnow())
        tex = None if texture0 is None else texture("texture0", texture0)
        if attack_state0 is not None:
            mapping("attack_state0", attack_state0, " (see state_to_dict) or None")
        try:
            if tex is not None:
                self.blobs.put_array(texture_blob_key(run.id, 0), tex)
            if attack_state0 is not None:
                doc = _state_doc(self.blobs, run.id, "attack_state0", attack_state0, arrays0)
                row["attack_state_ref"] = self.blobs.put_json(attack_state_key(run.id, 0), doc)
            with self._tx("create_run", write=True) as s:
                self._insert_runs(s, [row], sweep_id)
        except BaseException:
            self.blobs.delete_prefix(run_prefix(run.id))
            raise
        return run.id

    def create_runs(self, runs: Sequence[NewRun], sweep_id: str | None = None) -> list[str]:
        """Record ``runs`` (queued, iteration 0, in sweep ``sweep_id`` if given) all or nothing:
        every row is checked first, then one transaction inserts them (a few statements however
        many runs); an error or an interrupt before it commits leaves none. Returns their ids."""
        rows = self._run_rows(runs, sweep_id)
        with self._tx("create_runs", write=True) as s:
            self._insert_runs(s, rows, sweep_id)
        return [row["id"] for row in rows]

    @staticmethod
    def _run_rows(runs: Sequence[NewRun], sweep_id: str | None) -> list[dict[str, Any]]:
        """The rows of ``runs``, checked, ``created`` a microsecond apart so they list in this order."""
        now = utcnow()
        return [run_row(run, sweep_id, now + dt.timedelta(microseconds=i)) for i, run in enumerate(runs)]

    @staticmethod
    def _insert_runs(s: Session, rows: list[dict[str, Any]], sweep_id: str | None) -> None:
        if sweep_id is not None and s.get(Sweep, sweep_id) is None:
            raise StoreError(f"sweep {sweep_id!r}: not found")
        if rows:  # one executemany (the same columns in each row), sent as multi-row INSERTs
            s.execute(insert(Run), rows)

    def start_run(self, run_id: str, texture0: np.ndarray, attack_state0: Mapping[str, Any],
                  arrays0: Mapping[str, np.ndarray] | None = None) -> bool:
        """Record a run's starting texture and attack state, once: True for the caller that
        did, False when they were already there (nothing written)."""
        tex = texture("texture0", texture0)
        with self._tx("start_run", write=True) as s:
            run = self._run(s, run_id)
            if run.attack_state_ref is not None or run.iteration != 0:
                return False
            self.blobs.put_array(texture_blob_key(run_id, 0), tex)
            doc = _state_doc(self.blobs, run_id, "attack_state0", attack_state0, arrays0)
            run.attack_state_ref = self.blobs.put_json(attack_state_key(run_id, 0), doc)
        return True

    def get_run(self, run_id: str) -> RunSnapshot:
        """The run as stored."""
        with self._tx("get_run", write=False) as s:
            return self._run_snapshot(s, run_id)

    def find_run(self, ref: str) -> RunSnapshot:
        """The run whose id is ``ref`` or starts with it (at least 4 characters, unique)."""
        if not isinstance(ref, str) or not ref:
            raise StoreError(f"run {ref!r}: not found")
        with self._tx("find_run", write=False) as s:
            row = s.get(Run, ref)
            if row is not None:
                return RunSnapshot.of(row)
            rows = [RunSnapshot.of(r) for r in
                    s.scalars(select(Run).where(Run.id.startswith(ref, autoescape=True)).limit(2))]
        if len(ref) < 4 or not rows:
            raise StoreError(f"run {ref!r}: not found")
        if len(rows) > 1:
            raise StoreError(f"run {ref!r}: ambiguous (several run ids start with it); give more of the id")
        return rows[0]

    def runs(self, status: str | None = None, sweep_id: str | None = None) -> list[RunSnapshot]:
        """Every run (or those with ``status``, of sweep ``sweep_id``), oldest first."""
        query = select(Run).order_by(Run.created, Run.id)
        if status is not None:
            query = query.where(Run.status == self._check_status(status))
        if sweep_id is not None:
            query = query.where(Run.sweep_id == sweep_id)
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

    def transition(self, run_id: str, sources: tuple[str, ...], status: str,
                   error: str | None = None) -> bool:
        """Compare-and-set the status: move to ``status`` only from one of ``sources``
        (each an allowed transition); True when it moved, False when the run was elsewhere."""
        self._check_status(status)
        bad = [src for src in sources if status not in TRANSITIONS[self._check_status(src)]]
        if bad:
            raise StoreError(f"status transition {bad[0]} → {status} is not allowed")
        with self._tx("transition", write=True) as s:
            self._run(s, run_id)
            result = s.execute(
                update(Run).where(Run.id == run_id, Run.status.in_(sources))
                .values(status=status, error=error).execution_options(synchronize_session=False))
            return result.rowcount == 1

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
        self._frame_counts.pop(run_id, None)
        self.blobs.delete_prefix(run_prefix(run_id))

    # -- sweeps ----------------------------------------------------------------

    def create_sweep(self, name: str, spec: Mapping[str, Any], runs: Sequence[NewRun] = ()) -> str:
        """A new sweep and its ``runs``, all or nothing in one transaction (see :meth:`create_runs`);
        returns the sweep's id (the runs' ids are their ``NewRun.id``)."""
        sweep_id = str(uuid.uuid4())
        row = Sweep(id=sweep_id, name=check_name(name), spec_json=dumps("spec", dict(spec)))
        rows = self._run_rows(runs, sweep_id)
        with self._tx("create_sweep", write=True) as s:
            s.add(row)
            s.flush()  # the sweep row before its runs (their foreign key)
            self._insert_runs(s, rows, None)
        return sweep_id

    def find_sweep(self, ref: str) -> SweepSnapshot:
        """The sweep with id ``ref`` (or an id starting with it), else the latest named ``ref``."""
        with self._tx("find_sweep", write=False) as s:
            row = s.get(Sweep, ref) if isinstance(ref, str) else None
            if row is None and isinstance(ref, str) and len(ref) >= 4:
                rows = list(s.scalars(select(Sweep).where(Sweep.id.startswith(ref, autoescape=True))
                                      .limit(2)))
                row = rows[0] if len(rows) == 1 else None
            if row is None and isinstance(ref, str):
                row = s.scalars(select(Sweep).where(Sweep.name == ref)
                                .order_by(Sweep.created.desc()).limit(1)).first()
            if row is None:
                raise StoreError(f"sweep {ref!r}: not found (give a sweep id or name)")
            return SweepSnapshot.of(row)

    # -- textures and attack states ------------------------------------------

    def has_texture(self, run_id: str, k: int) -> bool:
        return self.blobs.exists(texture_blob_key(run_id, integer("k", k, 0)))

    def texture(self, run_id: str, k: int) -> np.ndarray:
        """Texture ``k`` of the run (H×W×3 sRGB, 0–1)."""
        key = texture_blob_key(run_id, integer("k", k, 0))
        if not self.blobs.exists(key):
            raise StoreError(f"run {run_id!r}: no texture for iteration {k} (blob {key!r} missing)")
        return self.blobs.get_array(key)

    def put_texture(self, run_id: str, k: int, texture_k: np.ndarray) -> None:
        """Store texture ``k`` (H×W×3 sRGB, 0–1) outside :meth:`advance` (e.g. evaluation)."""
        arr = texture("texture", texture_k)
        key = texture_blob_key(run_id, integer("k", k, 0))
        self.get_run(run_id)
        self.blobs.put_array(key, arr)

    def put_final_texture(self, run_id: str, texture_final: np.ndarray) -> None:
        """Store the texture the adversarial evaluation renders (H×W×3 sRGB, 0–1)."""
        arr = texture("texture_final", texture_final)
        self.get_run(run_id)
        self.blobs.put_array(final_texture_key(run_id), arr)

    def has_final_texture(self, run_id: str) -> bool:
        """Whether the run's final texture is chosen (a blob lookup; nothing read, no query)."""
        return self.blobs.exists(final_texture_key(run_id))

    def final_texture(self, run_id: str) -> np.ndarray | None:
        """The texture the adversarial evaluation renders; None until it is chosen."""
        key = final_texture_key(run_id)
        return self.blobs.get_array(key) if self.blobs.exists(key) else None

    def attack_state(self, run_id: str, k: int) -> dict[str, Any] | None:
        """The attack state stored with texture ``k``, its arrays read back as numpy arrays;
        None when there is none (a run created without ``attack_state0``, at k = 0)."""
        key = attack_state_key(run_id, integer("k", k, 0))
        self.get_run(run_id)
        if not self.blobs.exists(key):
            return None
        doc = self.blobs.get_json(key)
        return {name: self.blobs.get_array(v["array"]) if isinstance(v, dict) and set(v) == {"array"}
                else v for name, v in doc.items()}

    def advance(self, run_id: str, k: int, texture_next: np.ndarray,
                attack_state: Mapping[str, Any], record: Mapping[str, Any],
                arrays: Mapping[str, np.ndarray] | None = None) -> bool:
        """Compare-and-set the run from iteration ``k`` to ``k+1``.

        In one transaction: ``iteration`` goes from ``k`` to ``k+1`` only if it is
        still ``k`` and the run is queued or running; the winner writes texture
        ``k+1`` (H×W×3 sRGB, 0–1), the attack state for ``k+1`` (plain JSON, e.g.
        ``state_to_dict(state)``, with its arrays in ``arrays``) and the
        :class:`IterationRecord` of step ``k`` (fields ``RECORD_FIELDS``) before it
        commits; if a blob write fails, nothing is committed.

        Returns True for the caller that advanced the run, False when the run is
        already past ``k`` (another caller won) or no longer active (cancelled,
        failed, evaluating, done); nothing is written then. StoreError when the
        run is behind ``k`` or missing.
        """
        k = integer("k", k, 0, 2**31 - 2)
        tex = texture("texture_next", texture_next)
        mapping("attack_state", attack_state, " (see state_to_dict)")
        values = record_values(record)
        state_key = attack_state_key(run_id, k + 1)
        with self._tx("advance", write=True) as s:
            result = s.execute(
                update(Run).where(Run.id == run_id, Run.iteration == k, Run.status.in_(ACTIVE))
                .values(iteration=k + 1, attack_state_ref=state_key)
                .execution_options(synchronize_session=False))
            if result.rowcount != 1:
                run = self._run(s, run_id)
                if run.iteration > k or run.status not in ACTIVE:
                    return False
                raise StoreError(f"run {run_id!r}: cannot advance from iteration {k}; "
                                 f"the run is at iteration {run.iteration}")
            self.blobs.put_array(texture_blob_key(run_id, k + 1), tex)
            self.blobs.put_json(state_key, _state_doc(self.blobs, run_id, "attack_state",
                                                      attack_state, arrays))
            s.add(IterationRecord(run_id=run_id, k=k, **values))
        return True

    def drop_gradients(self, run_id: str, k: int | None = None) -> int:
        """Delete the frame gradients of iteration ``k`` (None: every iteration) of the run; returns
        how many. Call it once the iteration is reduced (:meth:`advance` returned True, or the run is
        past ``k``): nothing reads them then. The jobs' ``grad_ref`` keep naming the deleted blobs."""
        return self.blobs.delete_prefix(grad_prefix(run_id, None if k is None else integer("k", k, 0)))

    def put_seen_mask(self, run_id: str, seen: np.ndarray) -> None:
        """Store the run's seen-texel mask (H×W bool: texels some frame of iteration 0 sees)."""
        arr = np.asarray(seen)
        if arr.dtype != np.bool_ or arr.ndim != 2:
            raise StoreError(f"seen: must be an H×W bool mask, got {arr.dtype} {arr.shape}")
        self.blobs.put_array(seen_key(run_id), arr)

    def seen_mask(self, run_id: str) -> np.ndarray | None:
        """The run's seen-texel mask (:meth:`put_seen_mask`); None when there is none."""
        key = seen_key(run_id)
        return self.blobs.get_array(key) if self.blobs.exists(key) else None

    def iterations(self, run_id: str) -> list[IterationSnapshot]:
        """The run's iteration records, by ``k``."""
        with self._tx("iterations", write=False) as s:
            self._run(s, run_id)
            rows = s.scalars(select(IterationRecord).where(IterationRecord.run_id == run_id)
                             .order_by(IterationRecord.k))
            return [IterationSnapshot.of(r) for r in rows]

    def iterations_of(self, run_ids: Sequence[str]) -> dict[str, list[IterationSnapshot]]:
        """Each run's iteration records (by ``k``) for the runs ``run_ids``, in one query per
        :data:`IN_CHUNK` runs (a list page); an unknown id maps to ``[]``."""
        out: dict[str, list[IterationSnapshot]] = {run_id: [] for run_id in run_ids}
        ids = list(out)
        with self._tx("iterations_of", write=False) as s:
            for i in range(0, len(ids), IN_CHUNK):
                query = (select(IterationRecord).where(IterationRecord.run_id.in_(ids[i:i + IN_CHUNK]))
                         .order_by(IterationRecord.run_id, IterationRecord.k))
                for row in s.scalars(query):
                    out[row.run_id].append(IterationSnapshot.of(row))
        return out


__all__ = ["JOB_STATUSES", "NewRun", "RECORD_FIELDS", "RUN_STATUSES", "TRANSITIONS", "Store"]
