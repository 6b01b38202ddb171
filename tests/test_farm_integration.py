"""The farm for real: Redis, ``undream worker`` subprocesses, SQLite and PostgreSQL, crashes.

Every run here is also run by ``undream run`` in this process (the same
config and seed); the farm's final texture must equal it bit for bit.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from scheduler.iteration import attacked_frames

from conftest import s3_bucket
from farm_support import Farm, PrivateRedis, farm_inputs, fresh_postgres, run_config, wait_for, write_yaml



@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    return {**farm_inputs(tmp_path_factory, "farm_int", 4), "refs": {}}


def reference(tiny, **cfg) -> np.ndarray:
    """The final texture ``undream run`` gives for this config (computed once per config)."""
    from scheduler.local import run_local
    from undream.spec.run import RunConfig

    config = run_config(tiny["scene"], tiny["victim"], **cfg)
    key = repr(sorted(config.items()))
    if key not in tiny["refs"]:
        out = tiny["root"] / f"ref{len(tiny['refs'])}"
        run_local(RunConfig.from_json(config), out, progress=False)
        tiny["refs"][key] = np.load(out / "texture_final.npy")
    return tiny["refs"][key]


def submit(farm: Farm, tiny, name: str, *extra: str, **cfg) -> str:
    path = write_yaml(farm.root / f"{name}.yaml", run_config(tiny["scene"], tiny["victim"], name=name, **cfg))
    return farm.submit(path, *extra)


def final_texture(farm: Farm, run_id: str) -> np.ndarray:
    run = farm.store.get_run(run_id)
    name = f"{run.name}-{run_id[:8]}"
    if run.out_dir:
        out = Path(run.out_dir)
    elif farm.own_folders:  # blobs in the database or S3: on the worker that finished the run
        (out,) = farm.root.glob(f"cache*/outputs/{name}")
    else:
        out = farm.blobs / "outputs" / name
    return np.load(out / "texture_final.npy")


@pytest.fixture(scope="module")
def sqlite_farm(tiny):
    farm = Farm(tiny["root"] / "sqlite")
    farm.root.mkdir()
    farm.start_worker()
    yield farm
    farm.stop()


def test_a_submitted_run_completes_on_a_worker_like_the_local_run(sqlite_farm, tiny):
    farm = sqlite_farm
    out = farm.root / "out_a"
    run_id = submit(farm, tiny, "a", "--out", str(out))
    run = farm.wait_status(run_id)
    for name in ("texture_final.png", "texture_final.npy", "results.json", "loss.png", "metadata.json"):
        assert (out / name).is_file(), name
    assert len(list((out / "frames_benign").glob("*.png"))) == 4
    assert np.array_equal(np.load(out / "texture_final.npy"), reference(tiny))
    assert [r.k for r in farm.store.iterations(run_id)] == [0, 1, 2]
    assert run.farm["frames_per_task"] == 2 and run.scene_ref.startswith("scenes/")
    table = farm.cli("status")
    assert table.returncode == 0 and run_id[:8] in table.stdout and "done" in table.stdout
    detail = farm.cli("status", run_id[:8])
    assert detail.returncode == 0 and "adversarial jobs, k=3" in detail.stdout
    assert detail.stdout.count("succeeded") == 4


def test_a_short_run_finishes_while_a_long_one_runs(sqlite_farm, tiny):
    """Runs interleave per iteration (one chord in flight per run, FIFO queue): no starvation."""
    farm = sqlite_farm
    long_id = submit(farm, tiny, "long", steps=1000)
    farm.wait_status(long_id, ("running",))
    wait_for(lambda: farm.store.get_run(long_id).iteration >= 1, 60, "the long run to step")
    short_id = submit(farm, tiny, "short", steps=1)
    farm.wait_status(short_id, ("done",), timeout=60)
    long_run = farm.store.get_run(long_id)
    assert long_run.status == "running" and long_run.iteration < 1000
    res = farm.cli("cancel", long_id)
    assert res.returncode == 0 and f"cancelled {long_id}" in res.stdout
    stopped = farm.store.get_run(long_id).iteration
    time.sleep(1.5)
    assert farm.store.get_run(long_id).iteration <= stopped + 1  # at most the step in flight
    assert farm.store.get_run(long_id).status == "cancelled"


def _blob_farm(tiny, request, blobs: str, name: str, **settings) -> tuple[Farm, list]:
    """A farm whose blobs are in a folder (its SQLite file there too), or in PostgreSQL's ``blobs``
    table (``database``), or in S3 with the database in PostgreSQL; then no folder is shared."""
    if blobs == "folder":
        return Farm(tiny["root"] / name, **settings), []
    url, drop = fresh_postgres()
    if blobs == "database":
        return Farm(tiny["root"] / name, database_url=url, blob_url="database", **settings), [drop]
    server = request.getfixturevalue("s3_server")
    bucket = s3_bucket(server, f"farm-{name.replace('_', '-')}")
    farm = Farm(tiny["root"] / name, database_url=url, blob_url=f"s3://{bucket}/undream",
                s3_endpoint_url=server["endpoint"], s3_region="us-east-1",
                s3_access_key_id=server["key_id"], s3_secret_access_key=server["secret"], **settings)
    return farm, [drop]


@pytest.mark.parametrize("blobs", ["folder", "database", "s3"])
def test_sigkill_of_a_worker_mid_iteration_loses_nothing(tiny, request, blobs):
    """Two workers; the one running a frame job of iteration 1 or later is SIGKILLed (with its child).

    Its job goes back to Redis after the visibility timeout and runs on the
    other worker; every iteration is applied once and the texture is the
    undisturbed run's, bit for bit. On every blob backend: a folder, PostgreSQL's
    ``blobs`` table, S3 (those two with no folder shared between the workers).
    The finished run keeps no gradient (transient blobs).
    """
    farm, cleanup = _blob_farm(tiny, request, blobs, f"kill_{blobs}", frames_per_task=1)
    farm.root.mkdir()
    try:
        # Queued first, the workers started after: with batched frames a tiny frame job takes
        # tens of milliseconds, and the whole run could end before `undream submit` returns.
        # sim_spp 256 keeps each job long enough to be caught running.
        cfg = {"steps": 4, "sim_spp": 256, "grad_spp": 16}
        run_id = submit(farm, tiny, "kill", **cfg)
        workers = [farm.start_worker(), farm.start_worker()]

        def started_job():
            run = farm.store.get_run(run_id)
            jobs = [j for j in farm.store.jobs(run_id, run.iteration) if j.status == "started" and j.worker]
            return run.iteration >= 1 and jobs and jobs[0]

        job = wait_for(started_job, 90, "a started frame job of iteration >= 1", interval=0.005)
        pgid = os.getpgid(int(job.worker.split(":")[1]))
        victim = next(w for w in workers if w.pid == pgid)
        farm.kill_worker(victim)
        run = farm.wait_status(run_id, timeout=90)
        records = farm.store.iterations(run_id)
        attacked = attacked_frames(run)  # the 4-frame scene holds frame 3 out (holdout: auto)
        assert [r.k for r in records] == [0, 1, 2, 3] and all(r.n_ok == len(attacked) == 3 for r in records)
        again = next(j for j in farm.store.jobs(run_id, job.k) if j.frame == job.frame)
        assert again.status == "succeeded" and again.attempts >= 2  # ran again after the kill
        assert run.failures == 0
        assert np.array_equal(final_texture(farm, run_id), reference(tiny, **cfg))
        assert farm.store.blobs.listing(f"runs/{run_id}/grad") == [] and farm.store.seen_mask(run_id) is not None
        if farm.own_folders:
            assert not farm.blobs.exists() and farm.store.blobs.exists(run.scene_ref)
    finally:
        farm.stop()
        for drop in cleanup:
            drop()


def test_a_run_on_postgresql(tiny):
    url, drop = fresh_postgres()
    farm = Farm(tiny["root"] / "pg", database_url=url)
    farm.root.mkdir()
    try:
        farm.start_worker()
        run_id = submit(farm, tiny, "pg")
        farm.wait_status(run_id)
        assert farm.store.engine.dialect.name == "postgresql"
        assert np.array_equal(final_texture(farm, run_id), reference(tiny))
    finally:
        farm.stop()
        drop()


@pytest.fixture
def broker(tmp_path):
    """A Redis server of the test's own, to SIGKILL (the machine's serves the other farms meanwhile)."""
    server = PrivateRedis(tmp_path / "redis")
    yield server
    server.stop()


def test_a_run_survives_a_broker_restart_with_resume(tiny, broker):
    """Redis is SIGKILLed mid-run and started again (empty: no persistence); `undream resume` finishes."""
    farm = Farm(tiny["root"] / "broker", redis=broker)
    farm.root.mkdir()
    try:
        farm.start_worker()
        cfg = {"steps": 24, "sim_spp": 128, "grad_spp": 16}  # long enough to be mid-attack when Redis dies
        run_id = submit(farm, tiny, "broker", **cfg)
        wait_for(lambda: farm.store.get_run(run_id).iteration >= 1, 60, "the run to step", interval=0.02)
        broker.kill()
        at_kill = farm.store.get_run(run_id).iteration
        broker.start()
        time.sleep(2)
        # A callback that was publishing when Redis died may have gone on by itself, as far as the
        # evaluation (or failed the run when its publish gave up); queued jobs and chord counters are
        # gone either way.
        assert farm.store.get_run(run_id).status in ("running", "evaluating", "failed", "done")
        res = farm.cli("resume", run_id)
        assert res.returncode == 0, res.stderr
        assert f"resumed {run_id}" in res.stdout or f"run {run_id} is done" in res.stdout
        farm.wait_status(run_id, timeout=90)
        assert [r.k for r in farm.store.iterations(run_id)] == list(range(24)) and at_kill < 24
        assert np.array_equal(final_texture(farm, run_id), reference(tiny, **cfg))
    finally:
        if not broker.up():
            broker.start()  # the workers stop cleanly against a live broker
        farm.stop()
