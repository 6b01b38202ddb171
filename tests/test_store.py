"""The run store on SQLite and PostgreSQL: round trips, compare-and-set, transitions, blobs.

PostgreSQL tests use a fresh database per test, created and dropped through
``UNDREAM_TEST_POSTGRES_URL`` (default: the local server's ``test`` database as
user ``postgres``); they are skipped, saying why, when that server is unreachable.
"""
from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

from conftest import service_missing
from sqlalchemy import create_engine, event, func, select, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import SQLAlchemyError

from undream.errors import StoreError
from undream.store import (
    BlobStore, EvalResult, JobResult, NewRun, Store, attack_state_key, grad_key, open_store, texture_blob_key,
)
from undream.store import blobs as blobs_module
from undream.store.models import Run, Sweep

PG_ADMIN_URL = os.environ.get("UNDREAM_TEST_POSTGRES_URL",
                              "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def _texture(value: float = 0.25, shape: tuple[int, int] = (4, 5)) -> np.ndarray:
    return np.full((*shape, 3), value, dtype=np.float32)


# -- fixtures -----------------------------------------------------------------


@pytest.fixture(scope="session")
def pg_admin():
    """An autocommit engine on the PostgreSQL server, or a skip saying why there is none."""
    pytest.importorskip("psycopg", reason="psycopg not installed (pip install 'undream[postgres]')")
    engine = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT",
                           connect_args={"connect_timeout": 3})
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except SQLAlchemyError as exc:
        engine.dispose()
        service_missing(f"PostgreSQL unreachable at {make_url(PG_ADMIN_URL).render_as_string()}: "
                        f"{str(exc.orig or exc).splitlines()[0]}")
    yield engine
    engine.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path: Path):
    """A database URL for an empty store: SQLite in tmp_path, or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'runs.db'}"
        return
    admin = request.getfixturevalue("pg_admin")
    name = f"undream_test_{uuid.uuid4().hex[:12]}"
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield admin.url.set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))


@pytest.fixture
def store(db_url: str, tmp_path: Path):
    with open_store(db_url, tmp_path / "blobs") as s:
        yield s


@pytest.fixture
def run_id(store: Store) -> str:
    return store.create_run("demo", {"attack": {"name": "pgd", "eps": 8.0}}, n_frames=4,
                            seed=123, texture0=_texture(), attack_state0={"step": 0})


def _advance(store: Store, run_id: str, k: int, value: float = 0.5) -> bool:
    return store.advance(run_id, k, _texture(value), {"step": k + 1},
                         {"loss_mean": 1.5, "n_ok": 3, "n_bad": 1, "dropped_frames": [2],
                          "grad_norm": 2.0,
                          "step_seconds": 0.1, "per_frame": [1.0, 2.0, float("nan"), 1.5]})


# -- runs -----------------------------------------------------------------------


def test_run_round_trip(store: Store, run_id: str):
    run = store.get_run(run_id)
    assert (run.name, run.status, run.iteration, run.n_frames, run.seed) == ("demo", "queued", 0, 4, 123)
    assert run.config == {"attack": {"name": "pgd", "eps": 8.0}}
    assert run.error is None and run.results is None
    assert run.attack_state_ref == attack_state_key(run_id, 0)
    assert run.created.tzinfo is not None
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.status = "done"  # type: ignore[misc]
    got = store.texture(run_id, 0)
    assert got.dtype == np.float32 and np.array_equal(got, _texture())
    assert store.attack_state(run_id, 0) == {"step": 0}
    assert [r.id for r in store.runs()] == [run_id]
    assert store.runs(status="running") == []


def test_reopen_keeps_runs(db_url: str, tmp_path: Path):
    with open_store(db_url, tmp_path / "blobs") as first:
        rid = first.create_run("kept", {}, 1, 0, _texture())
    with open_store(db_url, tmp_path / "blobs") as second:
        assert second.get_run(rid).name == "kept"
        assert second.attack_state(rid, 0) is None  # created without a starting state
        assert np.array_equal(second.texture(rid, 0), _texture())


@pytest.mark.parametrize("kwargs, field", [
    ({"texture0": np.zeros((4, 4), np.float32)}, "texture0"),
    ({"texture0": np.full((4, 4, 3), 1.5, np.float32)}, "texture0"),
    ({"texture0": np.zeros((4, 4, 3), np.uint8)}, "texture0"),
    ({"n_frames": 0}, "n_frames"),
    ({"seed": -1}, "seed"),
    ({"name": ""}, "name"),
    ({"config": {"bad": object()}}, "config"),
    ({"attack_state0": {"m": float("nan")}}, "attack_state/000000.json"),
])
def test_create_run_rejects_bad_input(store: Store, kwargs: dict, field: str):
    args = {"name": "x", "config": {}, "n_frames": 2, "seed": 0, "texture0": _texture(), **kwargs}
    with pytest.raises(StoreError, match=field):
        store.create_run(**args)
    assert store.runs() == []
    assert not (store.blobs.root / "runs").exists() or not any((store.blobs.root / "runs").iterdir())


def test_unknown_run_is_named(store: Store):
    for call in (lambda: store.get_run("nope"), lambda: store.set_status("nope", "running"),
                 lambda: store.job_started("nope", 0, 0), lambda: store.iterations("nope"),
                 lambda: store.attack_state("nope", 1)):
        with pytest.raises(StoreError, match="run 'nope': not found"):
            call()


def test_status_transitions(store: Store, run_id: str):
    before = store.get_run(run_id).updated
    store.set_status(run_id, "running")
    assert store.get_run(run_id).updated > before
    store.set_status(run_id, "running")  # the callback may run twice
    store.set_status(run_id, "failed", error="frame 3 failed 3 times")
    assert store.get_run(run_id).error == "frame 3 failed 3 times"
    store.set_status(run_id, "queued")  # resume clears the error
    assert store.get_run(run_id).error is None
    for status in ("running", "evaluating", "done"):
        store.set_status(run_id, status)
    with pytest.raises(StoreError, match="done → running is not allowed"):
        store.set_status(run_id, "running")
    with pytest.raises(StoreError, match="'paused' is not a run status"):
        store.set_status(run_id, "paused")
    assert store.get_run(run_id).status == "done"


def test_results_and_delete(store: Store, run_id: str):
    store.set_results(run_id, {"asr": 0.75, "undefined": float("nan")})
    assert store.get_run(run_id).results == {"asr": 0.75, "undefined": None}
    store.job_started(run_id, 0, 1)
    assert _advance(store, run_id, 0)
    store.delete_run(run_id)
    assert store.runs() == []
    assert not (store.blobs.root / "runs" / run_id).exists()


# -- sweeps: recorded all or nothing ------------------------------------------------


def _new_runs(n: int) -> list[NewRun]:
    return [NewRun(f"grid-{i:03d}", {"attack": {"name": "pgd", "eps": 8.0 + i}}, n_frames=4, seed=i,
                   scene_ref="scenes/abc.tar", farm={"frames_per_task": 2}) for i in range(n)]


def _rows(store: Store) -> tuple[int, int]:
    """How many sweep and run rows the database holds (read past the store's own methods)."""
    with store.engine.connect() as conn:
        return tuple(conn.execute(select(func.count()).select_from(table)).scalar_one()
                     for table in (Sweep.__table__, Run.__table__))


def test_a_sweep_is_recorded_with_its_runs_in_order(store: Store):
    runs = _new_runs(5)
    sweep_id = store.create_sweep("grid", {"grid": {"attack.eps": [8, 9, 10, 11, 12]}}, runs)
    got = store.runs(sweep_id=sweep_id)
    assert [r.id for r in got] == [r.id for r in runs] and [r.name for r in got] == [r.name for r in runs]
    assert {(r.status, r.iteration, r.scene_ref) for r in got} == {("queued", 0, "scenes/abc.tar")}
    assert got[3].config == {"attack": {"name": "pgd", "eps": 11.0}} and got[3].farm == {"frames_per_task": 2}
    assert store.create_runs(_new_runs(2), sweep_id) and len(store.runs(sweep_id=sweep_id)) == 7
    with pytest.raises(StoreError, match="sweep 'nope': not found"):
        store.create_runs(_new_runs(1), "nope")


@pytest.mark.parametrize("interrupt", [KeyboardInterrupt, SystemExit])
def test_an_interrupted_sweep_records_no_sweep_and_no_run(store: Store, interrupt):
    """Ctrl-C (or SIGTERM, which the CLI turns into SystemExit) while the runs are inserted, after
    the sweep row was: the transaction never commits, so neither the sweep nor any run exists."""
    def stop(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        if statement.lstrip().upper().startswith("INSERT INTO RUNS"):
            raise interrupt()

    event.listen(store.engine, "before_cursor_execute", stop)
    try:
        with pytest.raises(interrupt):
            store.create_sweep("grid", {"grid": {}}, _new_runs(50))
    finally:
        event.remove(store.engine, "before_cursor_execute", stop)
    assert _rows(store) == (0, 0)
    store.create_sweep("grid", {"grid": {}}, _new_runs(3))  # the store works on afterwards
    assert _rows(store) == (1, 3)


def test_a_sweep_with_a_bad_run_records_nothing(store: Store):
    runs = _new_runs(4)
    with pytest.raises(StoreError, match=r"seed: must be an integer .* got -1"):  # checked before any write
        store.create_sweep("grid", {}, [*runs[:3], dataclasses.replace(runs[3], seed=-1)])
    with pytest.raises(StoreError, match="create_sweep: database error"):  # refused by the database
        store.create_sweep("grid", {}, [*runs[:3], dataclasses.replace(runs[3], id=runs[0].id)])
    assert _rows(store) == (0, 0)


def test_recording_a_sweep_takes_the_same_statements_for_5_runs_as_for_50(store: Store):
    seen: list[str] = []

    def count(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        seen.append(statement)

    counts = []
    event.listen(store.engine, "before_cursor_execute", count)
    try:
        for n in (5, 50):
            seen.clear()
            store.create_sweep("grid", {}, _new_runs(n))
            counts.append(len(seen))
    finally:
        event.remove(store.engine, "before_cursor_execute", count)
    assert counts[0] == counts[1] <= 4, counts  # (BEGIN,) INSERT sweep, INSERT runs: one transaction
    assert _rows(store) == (2, 55)


# -- frame jobs ---------------------------------------------------------------


def test_jobs_round_trip(store: Store, run_id: str):
    store.queue_jobs(run_id, 0, range(4))
    store.job_started(run_id, 0, 0)
    store.job_started(run_id, 0, 0)  # redelivered
    grad = np.random.default_rng(0).normal(size=(4, 5, 3)).astype(np.float32)
    store.job_succeeded(run_id, 0, 0, grad, loss=0.5, finite=True, timings={"render_s": 1.25})
    store.job_started(run_id, 0, 1)
    store.job_failed(run_id, 0, 1, "CUDA out of memory", will_retry=True)
    store.job_started(run_id, 0, 1)
    store.job_failed(run_id, 0, 1, "CUDA out of memory")
    store.job_started(run_id, 0, 2)
    store.job_succeeded(run_id, 0, 2, np.full((4, 5, 3), np.nan, np.float32),
                        loss=float("inf"), finite=False, timings={})

    jobs = {j.frame: j for j in store.jobs(run_id, 0)}
    assert [(jobs[f].status, jobs[f].attempts) for f in range(4)] == [
        ("succeeded", 2), ("failed", 2), ("succeeded", 1), ("queued", 0)]
    assert jobs[0].loss == 0.5 and jobs[0].finite and jobs[0].timings == {"render_s": 1.25}
    assert jobs[0].grad_ref == grad_key(run_id, 0, 0) and jobs[0].finished is not None
    assert jobs[1].error == "CUDA out of memory" and jobs[1].grad_ref is None
    assert jobs[2].loss is None and not jobs[2].finite
    assert store.jobs(run_id, 1) == []

    grads = store.frame_grads(run_id, 0)
    assert [(g.frame, g.loss, g.finite) for g in grads] == [
        (0, 0.5, True), (1, None, False), (2, None, False), (3, None, False)]
    assert np.array_equal(grads[0].grad, grad) and grads[1].grad is None
    assert np.isnan(grads[2].grad).all() and grads[3].grad is None


def test_job_rejects_bad_frame(store: Store, run_id: str):
    with pytest.raises(StoreError, match=r"frame: must be an integer in \[0, 3\], got 4"):
        store.job_started(run_id, 0, 4)
    with pytest.raises(StoreError, match="timings"):
        store.job_succeeded(run_id, 0, 0, np.zeros((4, 5, 3), np.float32), 0.1, True,
                            {"t": object()})


def test_concurrent_job_starts_count_every_attempt(store: Store, run_id: str):
    barrier = threading.Barrier(6)

    def start() -> None:
        barrier.wait()
        store.job_started(run_id, 0, 3)

    threads = [threading.Thread(target=start) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    (job,) = store.jobs(run_id, 0)
    assert (job.status, job.attempts) == ("started", 6)


# -- batches of frame jobs ------------------------------------------------------


def _results(n: int) -> list[JobResult]:
    """``n`` attack outcomes: frame 1 not finite, frame 2 without a result."""
    rng = np.random.default_rng(7)
    out = []
    for f in range(n):
        grad = rng.normal(size=(4, 5, 3)).astype(np.float32)
        if f == 1:
            grad[0, 0, 0] = np.nan
        out.append(JobResult(f, grad, float("inf") if f == 1 else 0.1 * f, f != 1,
                             {"render_s": 0.5 + f}, None if f == 2 else {"label": f"car{f}"}))
    return out


def _evals(n: int) -> list[EvalResult]:
    return [EvalResult(f, {"prediction": {"label": "car", "score": 0.1 * f}},
                       np.full((3, 2, 3), 10 * f, np.uint8), {"render_s": 0.25 * f}) for f in range(n)]


def _job_fields(store: Store, run_id: str, phase: str = "attack") -> list[tuple]:
    """What a reader sees of each job of iteration 0, times and the run's id left out."""
    return [(j.frame, j.status, j.attempts, j.loss, j.finite, j.timings, j.result, j.error, j.worker,
             None if j.grad_ref is None else j.grad_ref.replace(run_id, "RUN"),
             None if j.image_ref is None else j.image_ref.replace(run_id, "RUN"))
            for j in store.jobs(run_id, 0, phase)]


def _batch_run(store: Store, n_frames: int = 8) -> str:
    return store.create_run("batch", {}, n_frames=n_frames, seed=1, texture0=_texture())


def test_a_batch_reads_back_as_the_same_frames_one_by_one(store: Store):
    single, batch, results = _batch_run(store), _batch_run(store), _results(8)
    for r in results:
        store.job_started(single, 0, r.frame, worker="w:1")
        store.job_succeeded(single, 0, r.frame, r.grad, r.loss, r.finite, r.timings, r.result)
    store.jobs_started(batch, 0, range(8), worker="w:1")
    store.jobs_succeeded(batch, 0, results)

    assert _job_fields(store, batch) == _job_fields(store, single)
    assert [j.status for j in store.jobs(batch, 0)] == ["succeeded"] * 8
    for one, many in zip(store.frame_grads(single, 0), store.frame_grads(batch, 0)):
        assert (many.frame, many.loss, many.finite) == (one.frame, one.loss, one.finite)
        assert many.grad.dtype == np.float32 and np.array_equal(many.grad, one.grad, equal_nan=True)
    assert np.isnan(store.frame_grads(batch, 0)[1].grad[0, 0, 0])


def test_an_evaluation_batch_reads_back_as_the_same_frames_one_by_one(store: Store):
    single, batch, evals = _batch_run(store), _batch_run(store), _evals(8)
    for e in evals:
        store.job_started(single, 2, e.frame, "pre")
        store.eval_succeeded(single, 2, e.frame, "pre", e.result, e.image, e.timings)
    store.jobs_started(batch, 2, range(8), "pre")
    store.evals_succeeded(batch, 2, "pre", evals)

    def fields(run: str) -> list[tuple]:
        return [(j.frame, j.status, j.attempts, j.result, j.timings) for j in store.jobs(run, 2, "pre")]

    assert fields(batch) == fields(single)
    for job, e in zip(store.jobs(batch, 2, "pre"), evals):
        assert np.array_equal(store.blobs.get_array(job.image_ref), e.image)


def test_each_batch_start_counts_one_attempt(store: Store):
    run = _batch_run(store)
    store.queue_jobs(run, 0, range(8))
    store.queue_jobs(run, 0, [0, 0, 5])  # queued jobs are left alone, a repeated frame is one job
    store.jobs_started(run, 0, [0, 1, 2], worker="a:1")
    store.jobs_started(run, 0, [1, 2, 3], worker="b:2")  # 1 and 2 redelivered
    store.jobs_succeeded(run, 0, _results(3))
    jobs = store.jobs(run, 0)
    assert [(j.status, j.attempts) for j in jobs[:5]] == [
        ("succeeded", 1), ("succeeded", 2), ("succeeded", 2), ("started", 1), ("queued", 0)]
    assert [j.worker for j in jobs[:4]] == ["a:1", "b:2", "b:2", "b:2"]
    store.jobs_started(run, 0, [2])
    assert store.jobs(run, 0)[2].attempts == 3 and store.jobs(run, 0)[2].finished is None


def _bad(results: list, i: int, **change) -> list:
    return [dataclasses.replace(r, **change) if j == i else r for j, r in enumerate(results)]


@pytest.mark.parametrize("record, field", [
    (lambda s, run: s.jobs_started(run, 0, [0, 1, 8]), r"frame: must be an integer in \[0, 7\], got 8"),
    (lambda s, run: s.jobs_started(run, 0, [0, 1, 1]), "frames: frame 1 is given more than once"),
    (lambda s, run: s.jobs_started(run, 0, [0], phase="train"), "phase: 'train' is not a job phase"),
    (lambda s, run: s.queue_jobs(run, 0, [3, -1]), r"frame: must be an integer in \[0, 7\], got -1"),
    (lambda s, run: s.jobs_succeeded(run, 0, _bad(_results(8), 7, frame=8)),
     r"frame: must be an integer in \[0, 7\], got 8"),
    (lambda s, run: s.jobs_succeeded(run, 0, _bad(_results(8), 6, frame=3)), "frames: frame 3 is given"),
    (lambda s, run: s.jobs_succeeded(run, 0, _bad(_results(8), 5, grad=np.zeros((4, 5, 3), np.int32))),
     "grad: must be a float array, got dtype int32 .frame 5."),
    (lambda s, run: s.jobs_succeeded(run, 0, _bad(_results(8), 4, finite=1)),
     "finite: must be true or false"),
    (lambda s, run: s.jobs_succeeded(run, 0, _bad(_results(8), 3, timings={"t": object()})),
     "timings: not JSON"),
    (lambda s, run: s.jobs_succeeded(run, 0, [*_results(2), {"frame": 2}]),
     "results: each item must be a JobResult"),
    (lambda s, run: s.evals_succeeded(run, 0, "attack", _evals(8)), "phase: evaluation results belong"),
    (lambda s, run: s.evals_succeeded(run, 0, "pre", _bad(_evals(8), 7, frame=9)),
     r"frame: must be an integer in \[0, 7\], got 9"),
    (lambda s, run: s.evals_succeeded(run, 0, "pre", _bad(_evals(8), 2, image=np.zeros((3, 2, 3)))),
     "image: must be an H×W×3 uint8 sRGB frame, got float64"),
])
def test_a_bad_item_writes_nothing(store: Store, record, field: str):
    run = _batch_run(store)
    with pytest.raises(StoreError, match=field):
        record(store, run)
    assert store.jobs(run, 0) == [] and store.jobs(run, 0, "pre") == []
    assert not (store.blobs.root / "runs" / run / "grad").exists()
    assert not (store.blobs.root / "runs" / run / "eval").exists()


def test_a_batch_takes_the_same_number_of_statements_as_one_frame(store: Store):
    """Recording a batch is a constant number of SQL statements, whatever its size."""
    seen: list[str] = []

    def count(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        seen.append(statement)

    def statements(n: int) -> list[int]:
        run, counts = _batch_run(store, n_frames=8), []
        for record in (lambda: store.queue_jobs(run, 0, range(n)),
                       lambda: store.jobs_started(run, 0, range(n)),
                       lambda: store.jobs_succeeded(run, 0, _results(n)),
                       lambda: store.jobs_started(run, 3, range(n), "adversarial"),
                       lambda: store.evals_succeeded(run, 3, "adversarial", _evals(n))):
            seen.clear()
            record()
            counts.append(len(seen))
        return counts

    event.listen(store.engine, "before_cursor_execute", count)
    try:
        one, eight = statements(1), statements(8)
    finally:
        event.remove(store.engine, "before_cursor_execute", count)
    assert eight == one and max(eight) <= 4, (one, eight)  # BEGIN, SELECT n_frames; BEGIN, INSERT


# -- compare-and-set --------------------------------------------------------------


def test_advance_is_compare_and_set(store: Store, run_id: str):
    assert [_advance(store, run_id, 0), _advance(store, run_id, 0, value=0.9)] == [True, False]
    run = store.get_run(run_id)
    assert run.iteration == 1 and run.attack_state_ref == attack_state_key(run_id, 1)
    assert np.array_equal(store.texture(run_id, 1), _texture(0.5))  # the loser wrote nothing
    assert store.attack_state(run_id, 1) == {"step": 1}
    (rec,) = store.iterations(run_id)
    assert (rec.k, rec.loss_mean, rec.n_ok, rec.n_bad, rec.grad_norm) == (0, 1.5, 3, 1, 2.0)
    assert rec.dropped_frames == [2]
    assert rec.per_frame == [1.0, 2.0, None, 1.5]
    with pytest.raises(StoreError, match="cannot advance from iteration 3; the run is at iteration 1"):
        _advance(store, run_id, 3)
    assert _advance(store, run_id, 1)
    assert [r.k for r in store.iterations(run_id)] == [0, 1]


def test_advance_rejects_bad_record(store: Store, run_id: str):
    with pytest.raises(StoreError, match="unknown field.*loss_mena"):
        store.advance(run_id, 0, _texture(), {}, {"loss_mena": 1.0})
    assert store.get_run(run_id).iteration == 0


def test_advance_commits_nothing_when_a_blob_write_fails(store: Store, run_id: str, monkeypatch):
    def broken(key, data):
        raise StoreError(f"blob {key!r}: disk full")

    monkeypatch.setattr(store.blobs, "put_json", broken)
    with pytest.raises(StoreError, match="disk full"):
        _advance(store, run_id, 0)
    assert store.get_run(run_id).iteration == 0 and store.iterations(run_id) == []
    monkeypatch.undo()
    assert _advance(store, run_id, 0)  # the retried callback wins


def test_concurrent_advance_has_one_winner(db_url: str, tmp_path: Path, run_id: str):
    """Workers with their own engines (as separate processes would have) race on each k."""
    contenders = [open_store(db_url, tmp_path / "blobs") for _ in range(4)]
    try:
        for k in range(3):
            barrier = threading.Barrier(len(contenders))
            wins: list[bool] = []
            errors: list[BaseException] = []

            def race(s: Store, value: float, k: int = k) -> None:
                barrier.wait()
                try:
                    wins.append(_advance(s, run_id, k, value))
                except BaseException as exc:  # surfaced by the assert below
                    errors.append(exc)

            threads = [threading.Thread(target=race, args=(s, 0.1 * (i + 1)))
                       for i, s in enumerate(contenders)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            assert errors == [] and sorted(wins) == [False, False, False, True]
        assert contenders[0].get_run(run_id).iteration == 3
        assert [r.k for r in contenders[0].iterations(run_id)] == [0, 1, 2]
    finally:
        for s in contenders:
            s.close()


# -- blobs ------------------------------------------------------------------------


@pytest.mark.parametrize("key", ["../escape.npy", "/etc/passwd.npy", "runs/../../x.npy",
                                 "runs//x.npy", "", ".hidden.npy", "runs/a\\b.npy",
                                 "runs/x/.x.npy.abc.tmp", "runs/x/texture.txt"])
def test_blob_key_validation_names_the_key(tmp_path: Path, key: str):
    blobs = BlobStore(tmp_path)
    with pytest.raises(StoreError, match=re.escape(f"blob key {key!r}")):
        blobs.put_array(key, np.zeros(3))
    assert list(tmp_path.iterdir()) == []


def test_blob_round_trip(tmp_path: Path):
    blobs = BlobStore(tmp_path)
    arr = np.arange(24, dtype=np.float64).reshape(2, 3, 4)
    key = blobs.put_array(texture_blob_key("r1", 12), arr)
    assert key == "runs/r1/texture/000012.npy" and blobs.exists(key)
    assert np.array_equal(blobs.get_array(key), arr)
    blobs.put_json(attack_state_key("r1", 12), {"m": [1, 2], "x": None})
    assert blobs.get_json("runs/r1/attack_state/000012.json") == {"m": [1, 2], "x": None}
    with pytest.raises(StoreError, match="not strict JSON"):
        blobs.put_json("runs/r1/bad.json", {"v": float("nan")})
    with pytest.raises(StoreError, match="'runs/r2/texture/000000.npy': not found"):
        blobs.get_array(texture_blob_key("r2", 0))
    assert blobs.delete_prefix("runs/r1") == 2 and not blobs.exists(key)
    assert blobs.delete_prefix("runs/r1") == 0


def test_crash_before_replace_leaves_no_partial_blob(tmp_path: Path, monkeypatch):
    blobs = BlobStore(tmp_path)
    key = grad_key("r1", 3, 1)
    blobs.put_array(key, np.ones(8))

    def crash(src, dst):
        raise OSError("killed before rename")

    monkeypatch.setattr(blobs_module.os, "replace", crash)
    with pytest.raises(StoreError, match="'runs/r1/grad/000003/0001.npy': cannot write"):
        blobs.put_array(key, np.zeros(8))
    with pytest.raises(StoreError):
        blobs.put_array(grad_key("r1", 3, 2), np.zeros(8))
    monkeypatch.undo()
    assert np.array_equal(blobs.get_array(key), np.ones(8))  # the old content, whole
    assert not blobs.exists(grad_key("r1", 3, 2))
    assert [p.name for p in blobs.path(key).parent.iterdir()] == ["0001.npy"]  # no temp files


def test_crash_mid_write_leaves_no_partial_blob(tmp_path: Path, monkeypatch):
    blobs = BlobStore(tmp_path)

    def half_save(f, arr, allow_pickle=False):
        f.write(b"\x93NUMPY half a header")
        raise KeyboardInterrupt

    monkeypatch.setattr(blobs_module.np, "save", half_save)
    with pytest.raises(KeyboardInterrupt):
        blobs.put_array("runs/r1/texture/000001.npy", np.zeros(8))
    assert not blobs.exists("runs/r1/texture/000001.npy")
    monkeypatch.undo()

    def killed(fd):  # the bytes are in the temporary file, not yet on disk: the writer dies
        raise KeyboardInterrupt

    monkeypatch.setattr(blobs_module.os, "fsync", killed)
    with pytest.raises(KeyboardInterrupt):
        blobs.put_array("runs/r1/texture/000001.npy", np.zeros(8))
    assert list((tmp_path / "runs" / "r1" / "texture").iterdir()) == []


# -- opening --------------------------------------------------------------------


def test_default_store_is_sqlite_in_wal_mode(tmp_path: Path):
    with open_store(None, tmp_path / "farm") as s:
        assert (tmp_path / "farm" / "undream.db").is_file()
        with s.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1


@pytest.mark.parametrize("url, shown", [
    ("postgresql://alice:s3cret@127.0.0.1:1/farm", "postgresql://alice:***@127.0.0.1:1/farm"),
    ("postgresql://alice:s3cret@127.0.0.1:notaport/farm", "alice:***@127.0.0.1:notaport"),
    ("mysql://alice:s3cret@127.0.0.1/farm", "mysql://alice:***@127.0.0.1/farm"),
    ("not a url", "not a url"),
])
def test_bad_url_error_names_url_without_password(tmp_path: Path, url: str, shown: str):
    with pytest.raises(StoreError) as info:
        open_store(url, tmp_path)
    message = str(info.value)
    assert shown in message and "s3cret" not in message


def test_unopenable_sqlite_path_names_url(tmp_path: Path):
    url = f"sqlite:///{tmp_path / 'missing' / 'dir' / 'runs.db'}"
    with pytest.raises(StoreError, match="cannot open the run database at .*missing/dir/runs.db"):
        open_store(url, tmp_path / "blobs")


def test_store_imports_no_torch():
    code = "import sys, undream.store; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
