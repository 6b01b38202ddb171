"""A run is never left ``running`` by a dead process: leases, the stale-run rule, resume, the v2 → v3 upgrade.

Before the lease, a SIGKILLed ``undream run`` left its run ``running`` for
ever, and nothing could continue it. Now ``undream status`` finds the owner
gone and fails the run with the reason, and ``undream run --resume`` takes it
to the end, where an uninterrupted run ends (bit for bit).
"""
from __future__ import annotations

import datetime as dt
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import inspect, text

from farm_support import fresh_postgres, make_scene, make_victim, run_config, write_yaml
from scheduler.lease import Lease, expire_stale, process_gone, stale_reason, this_process
from undream.errors import StoreError
from undream.store import open_store
from undream.store.models import utcnow

ROOT = Path(__file__).resolve().parents[1]
HOST = socket.gethostname()


def _undream(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True,
                          cwd=ROOT)


@pytest.fixture
def store(tmp_path):
    with open_store(None, tmp_path / "store") as s:
        yield s


def _run(store, status: str = "running") -> str:
    run_id = store.create_run("lease", {}, n_frames=1, seed=0)
    if status != "queued":
        store.set_status(run_id, "running")
    return run_id


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


# -- the rule -------------------------------------------------------------------------------------


def test_a_dead_owner_on_this_host_makes_the_run_stale_at_once(store):
    run_id = _run(store)
    owner = f"{HOST}:{_dead_pid()}"
    assert store.claim(run_id, owner)
    reason = stale_reason(store.get_run(run_id), utcnow())
    assert reason is not None and owner in reason and "is gone" in reason and "--resume" in reason
    assert expire_stale(store) == [run_id]
    run = store.get_run(run_id)
    assert (run.status, run.error, run.owner) == ("failed", reason, None)


def test_an_owner_elsewhere_is_stale_only_after_the_lease(store):
    run_id = _run(store)
    assert store.claim(run_id, "farm-node-7:1234")
    now = utcnow()
    assert stale_reason(store.get_run(run_id), now) is None  # a fresh heartbeat from another host
    later = now + dt.timedelta(seconds=61)
    reason = stale_reason(store.get_run(run_id), later)
    assert reason is not None and "farm-node-7:1234" in reason and "lease 60 s" in reason


def test_a_live_owner_ended_runs_and_farm_runs_are_never_stale(store):
    live = _run(store)
    assert store.claim(live, this_process())
    ownerless = _run(store)  # a farm run: the broker redelivers its jobs
    done = _run(store)
    assert store.claim(done, f"{HOST}:{_dead_pid()}")
    store.set_status(done, "evaluating")
    store.set_status(done, "done")
    far_future = utcnow() + dt.timedelta(days=1)
    assert stale_reason(store.get_run(live), utcnow()) is None
    assert stale_reason(store.get_run(ownerless), far_future) is None
    assert stale_reason(store.get_run(done), far_future) is None
    assert expire_stale(store) == []


def test_expiry_loses_to_a_heartbeat_that_came_in_meanwhile(store):
    run_id = _run(store)
    assert store.claim(run_id, "elsewhere:1")
    judged_at = utcnow() - dt.timedelta(seconds=5)  # the stale verdict was taken before this beat
    assert store.beat(run_id, "elsewhere:1")
    assert not store.expire(run_id, "elsewhere:1", judged_at, "stale")
    assert store.get_run(run_id).status == "running"


def test_a_zombie_counts_as_gone():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 10
    while not Path(f"/proc/{child.pid}/stat").read_text().rpartition(")")[2].split()[0] == "Z":
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert process_gone(child.pid)  # exited, not yet reaped
    child.wait()
    assert process_gone(child.pid) and not process_gone(os.getpid())


# -- the lease -------------------------------------------------------------------------------------


def test_the_lease_beats_and_is_released(store):
    run_id = _run(store)
    with Lease(store, run_id, beat_s=0.05) as lease:
        first = store.get_run(run_id).heartbeat
        time.sleep(0.3)
        run = store.get_run(run_id)
        assert run.owner == lease.owner == this_process() and run.heartbeat > first
    assert store.get_run(run_id).owner is None


def test_a_run_held_by_a_live_process_is_refused_and_left_alone(store):
    run_id = _run(store)
    holder = f"{HOST}:{os.getppid()}"  # alive: the process that started the tests
    assert store.claim(run_id, holder)
    with pytest.raises(StoreError, match=rf"being run by {holder}"):
        with Lease(store, run_id):
            pass
    run = store.get_run(run_id)
    assert (run.status, run.owner) == ("running", holder)


# -- the schema upgrade ----------------------------------------------------------------------------


LIST_INDEXES = {"ix_runs_created_id", "ix_runs_status_created_id", "ix_runs_sweep_created_id", "ix_runs_owner"}
JOB_INDEXES = ["ix_frame_jobs_failed", "ix_frame_jobs_run_k_status"]


@pytest.mark.parametrize("version", [2, 3])
@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_an_older_database_is_upgraded_in_place(backend, version, tmp_path):
    """A database undream wrote with schema 2 (no leases) or 3 (no list indexes, no alembic) opens
    as schema 5: columns added by the hand-written step, indexes by alembic's revision 0004, the
    iterations' terms column by 0005."""
    drop = None
    if backend == "sqlite":
        url = f"sqlite:///{tmp_path / 'old.db'}"
    else:
        url, drop = fresh_postgres()
    try:
        _downgrade_and_reopen(url, tmp_path, version)
    finally:
        if drop is not None:
            drop()


def _downgrade_and_reopen(url: str, tmp_path: Path, version: int) -> None:
    with open_store(url, tmp_path / "blobs") as s:
        run_id = s.create_run("old", {"a": 1}, n_frames=2, seed=3)
        assert LIST_INDEXES <= {ix["name"] for ix in inspect(s.engine).get_indexes("runs")}
        with s.engine.begin() as conn:  # back to what undream with schema `version` wrote
            for name in sorted(LIST_INDEXES) + JOB_INDEXES:
                conn.execute(text(f"DROP INDEX {name}"))
            conn.execute(text("DROP TABLE alembic_version"))
            conn.execute(text("DROP TABLE blobs"))
            conn.execute(text("ALTER TABLE iterations DROP COLUMN terms_json"))
            if version == 2:
                conn.execute(text("ALTER TABLE runs DROP COLUMN owner"))
                conn.execute(text("ALTER TABLE runs DROP COLUMN heartbeat"))
            conn.execute(text("DELETE FROM undream_schema"))
            conn.execute(text(f"INSERT INTO undream_schema (version) VALUES ({version})"))
    with open_store(url, tmp_path / "blobs") as s:
        with s.engine.connect() as conn:
            assert conn.scalar(text("SELECT max(version) FROM undream_schema")) == 5
            assert conn.scalar(text("SELECT version_num FROM alembic_version")) == "0005"
        assert LIST_INDEXES <= {ix["name"] for ix in inspect(s.engine).get_indexes("runs")}
        assert set(JOB_INDEXES) <= {ix["name"] for ix in inspect(s.engine).get_indexes("frame_jobs")}
        assert "blobs" in inspect(s.engine).get_table_names()
        assert "terms_json" in {c["name"] for c in inspect(s.engine).get_columns("iterations")}
        run = s.get_run(run_id)
        assert (run.name, run.config, run.owner, run.heartbeat) == ("old", {"a": 1}, None, None)
        assert s.claim(run_id, "h:1") and s.get_run(run_id).owner == "h:1"
    with open_store(url, tmp_path / "blobs") as s:  # opened again: nothing left to do
        with s.engine.connect() as conn:
            assert conn.scalar(text("SELECT count(*) FROM undream_schema WHERE version = 5")) == 1


def test_a_schema_4_database_gains_the_terms_column(tmp_path):
    """Schema 4 (alembic 0004, no iterations.terms_json) opens as 5; its steps read back without terms."""
    url = f"sqlite:///{tmp_path / 'v4.db'}"
    with open_store(url, tmp_path / "blobs") as s:
        run_id = s.create_run("old", {"a": 1}, n_frames=2, seed=3)
        T = np.zeros((2, 2, 3), np.float32)
        s.put_texture(run_id, 0, T)
        assert s.advance(run_id, 0, T, {}, {"loss_mean": 1.5})
        with s.engine.begin() as conn:
            conn.execute(text("ALTER TABLE iterations DROP COLUMN terms_json"))
            conn.execute(text("UPDATE alembic_version SET version_num = '0004'"))
            conn.execute(text("DELETE FROM undream_schema"))
            conn.execute(text("INSERT INTO undream_schema (version) VALUES (4)"))
    with open_store(url, tmp_path / "blobs") as s:
        with s.engine.connect() as conn:
            assert conn.scalar(text("SELECT version_num FROM alembic_version")) == "0005"
        (rec,) = s.iterations(run_id)
        assert (rec.loss_mean, rec.terms) == (1.5, {})
        T1 = np.ones((2, 2, 3), np.float32)
        assert s.advance(run_id, 1, T1, {}, {"loss_mean": 1.0, "terms": {"reg_tv": 0.25}})
        assert s.iterations(run_id)[1].terms == {"reg_tv": 0.25}


# -- end to end: SIGKILL, status, resume ------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    base = tmp_path_factory.mktemp("stale")
    scene = make_scene(base / "scene", n_frames=4, size=24)
    victim = make_victim(base / "victim")
    return write_yaml(base / "run.yaml", run_config(scene, victim, name="stale", steps=12))


def _iteration(out: Path) -> int:
    try:
        with sqlite3.connect(out / "store" / "undream.db", timeout=1) as conn:
            row = conn.execute("SELECT iteration FROM runs").fetchone()
    except sqlite3.Error:
        return -1
    return -1 if row is None else row[0]


def test_a_killed_run_is_failed_by_status_and_resumes_to_the_uninterrupted_texture(tiny, tmp_path):
    reference, out = tmp_path / "reference", tmp_path / "killed"
    assert _undream("run", str(tiny), "--out", str(reference), "--no-progress").returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "run", str(tiny), "--out", str(out),
                             "--no-progress"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while _iteration(out) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, "the run ended before it was killed"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()

    status = _undream("status", "--out", str(out))
    assert status.returncode == 0, status.stderr
    assert "failed" in status.stdout and "running" not in status.stdout, status.stdout
    run_ref = status.stdout.splitlines()[1].split()[0]
    detail = _undream("status", run_ref, "--out", str(out)).stdout
    assert f"the process that ran it ({HOST}:{proc.pid}) is gone" in detail, detail

    resumed = _undream("run", str(tiny), "--out", str(out), "--resume", "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert "done" in _undream("status", "--out", str(out)).stdout
    np.testing.assert_array_equal(np.load(out / "texture_final.npy"), np.load(reference / "texture_final.npy"))


# The gradients are written without fsync (they live one iteration): a machine that loses power
# after the jobs' rows were committed can come back with a job "succeeded" and its gradient gone.
_POWER_CUT = """
import os, sys
import scheduler.stages as stages
step = stages._step
def cut(store, contexts, run, k, dispatch):
    if k == 2:  # iteration 2's jobs are recorded; one gradient did not reach the disk; the machine goes down
        job = store.jobs(run.id, k)[0]
        store.blobs.path(job.grad_ref).unlink()
        os._exit(9)
    return step(store, contexts, run, k, dispatch)
stages._step = cut
from undream.cli import main
main(sys.argv[1:])
"""


def test_a_gradient_lost_with_the_machine_is_computed_again_on_resume(tiny, tmp_path):
    reference, out = tmp_path / "reference", tmp_path / "cut"
    assert _undream("run", str(tiny), "--out", str(reference), "--no-progress").returncode == 0
    cut = subprocess.run([sys.executable, "-c", _POWER_CUT, "run", str(tiny), "--out", str(out), "--no-progress"],
                         cwd=ROOT, capture_output=True, text=True)
    assert cut.returncode == 9, cut.stderr
    assert _iteration(out) == 2

    resumed = _undream("run", str(tiny), "--out", str(out), "--resume", "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert "done" in _undream("status", "--out", str(out)).stdout
    np.testing.assert_array_equal(np.load(out / "texture_final.npy"), np.load(reference / "texture_final.npy"))


def test_resume_refuses_another_config_and_a_folder_without_a_run(tiny, tmp_path):
    import yaml

    out = tmp_path / "done"
    assert _undream("run", str(tiny), "--out", str(out), "--no-progress").returncode == 0
    other = yaml.safe_load(tiny.read_text())
    other["attack"]["eps"] = 64.0
    changed = write_yaml(tiny.parent / "other.yaml", other)
    res = _undream("run", str(changed), "--out", str(out), "--resume")
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "another config (attack differ)" in res.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    res = _undream("run", str(tiny), "--out", str(empty), "--resume")
    assert res.returncode == 2 and "has none" in res.stderr and not any(empty.iterdir())
    res = _undream("run", str(tiny), "--out", str(out), "--resume", "--force")
    assert res.returncode == 2 and "give one of them" in res.stderr
    again = _undream("run", str(tiny), "--out", str(out), "--resume", "--no-progress")
    assert again.returncode == 0 and "results in" in again.stdout  # a done run: its results
