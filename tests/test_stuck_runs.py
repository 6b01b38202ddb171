"""Runs that cannot make progress are visible (issue 24): waiting on a queue no live worker
consumes, or failing with the reason, in ``undream status``, on the workers page and in
``/api/workers``; the workers page reads the store in a fixed number of queries."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import service_missing  # noqa: E402
from farm_support import Farm, free_db, redis_client, redis_up, release_db, sql_statements, wait_for  # noqa: E402

from undream.cli import main  # noqa: E402
from undream.dashboard import create_app  # noqa: E402
from undream.settings import load_settings  # noqa: E402
from undream.spec.run import RunConfig  # noqa: E402
from undream.store import open_store  # noqa: E402
from workers.health import Consumers, probe, stuck_runs  # noqa: E402
from workers.presence import PREFIX, announce, live_queues  # noqa: E402
from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE, QUEUES  # noqa: E402

SECRET = "hunter2-secret"
ERROR = f"RenderError: cannot load scene from\n  postgresql://farm:{SECRET}@db:5432/undream (timeout)"
NO_BROKER = "redis://127.0.0.1:1/0"  # refused at once: the live queues are unknown


def _run(store, name: str) -> str:
    config = RunConfig.from_json({"scene": "s", "name": name, "attack": {"name": "pgd", "steps": 2}})
    return store.create_run(config.name, config.to_json(), 3, 0)


def _farm(blobs: Path, n_queued: int = 1) -> dict[str, str]:
    """Queued runs (``queued``…), a running run with a job queued (``frames``), one whose job failed
    twice with a password in its error (``failing``) and one driven by its own process (``local``)."""
    with open_store(None, blobs) as store:
        ids = {f"queued{i}": _run(store, f"queued{i}") for i in range(n_queued)}
        for name in ("frames", "failing", "local"):
            ids[name] = _run(store, name)
            store.transition(ids[name], ("queued",), "running")
            store.queue_jobs(ids[name], 0, [0, 1, 2])
        for attempt in range(2):
            store.job_started(ids["failing"], 0, 1, worker="node-a:7")
            store.job_failed(ids["failing"], 0, 1, ERROR, will_retry=attempt == 0)
        store.job_started(ids["frames"], 0, 0, worker="node-a:8")
        assert store.claim(ids["local"], "node-b:9")
    return ids


def _health(blobs: Path, consumers: Consumers) -> dict:
    with open_store(None, blobs) as store:
        return stuck_runs(store, lambda: consumers)


def test_runs_on_queues_without_a_live_worker_wait_and_failing_jobs_give_the_redacted_reason(tmp_path):
    ids = _farm(tmp_path)
    nobody = _health(tmp_path, Consumers({}))
    waiting = {r["run_id"]: r for r in nobody["waiting"]}
    assert waiting[ids["queued0"]]["queue"] == CONTROL_QUEUE  # its start waits for a worker
    assert waiting[ids["frames"]]["reason"] == f"no live worker on queue {FRAMES_QUEUE}"
    assert nobody["n_waiting"] == len(waiting) >= 3
    (failing,) = nobody["failing"]
    assert failing["run_id"] == ids["failing"] and failing["job"] == "attack k=0 frame 1"
    assert failing["reason"] == "RenderError: cannot load scene from postgresql://farm:***@db:5432/undream (timeout)"
    assert (failing["job_status"], failing["attempts"], failing["max_attempts"]) == ("failed", 2, 3)
    assert SECRET not in repr(nobody)

    frames_only = _health(tmp_path, Consumers({FRAMES_QUEUE: ("w1@host",)}))
    assert {r["run_id"] for r in frames_only["waiting"]} == {ids["queued0"]}  # only the control queue lacks one
    both = _health(tmp_path, Consumers({q: ("w1@host",) for q in QUEUES}))
    assert both["waiting"] == [] and both["n_waiting"] == 0 and both["n_failing"] == 1

    unknown = _health(tmp_path, Consumers(None, "cannot reach the broker"))
    assert unknown["queues"] is None and unknown["n_waiting"] is None and unknown["waiting"] == []
    assert unknown["broker_error"] == "cannot reach the broker" and unknown["n_failing"] == 1


def test_a_run_driven_by_its_own_process_never_waits_and_lists_are_capped(tmp_path):
    ids = _farm(tmp_path, n_queued=5)
    with open_store(None, tmp_path) as store:
        nobody = stuck_runs(store, lambda: Consumers({}))
        capped = stuck_runs(store, lambda: Consumers({}), limit=2)
        assert store.release(ids["local"], "node-b:9")  # its process let go: a run like the farm's now
        freed = stuck_runs(store, lambda: Consumers({}))
    assert ids["local"] not in {r["run_id"] for r in nobody["waiting"]} and nobody["n_waiting"] == 7  # 5 queued, frames, failing
    assert len(capped["waiting"]) == 2 and capped["n_waiting"] == 7
    assert [r["run_id"] for r in capped["waiting"]] == [r["run_id"] for r in nobody["waiting"][:2]]  # stalled longest
    assert freed["n_waiting"] == 8 and ids["local"] in {r["run_id"] for r in freed["waiting"]}


def test_status_lists_stuck_runs_after_its_table(tmp_path):
    _farm(tmp_path)
    env = {"UNDREAM_BLOB_URL": str(tmp_path), "UNDREAM_BROKER_URL": NO_BROKER, "UNDREAM_CONNECT_TIMEOUT": "1"}
    res = CliRunner().invoke(main, ["status"], env=env, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    table, stuck = res.output.split("\nlive queues: ")
    assert "queued0" in table and "failing" in table
    assert stuck.startswith(f"unknown (cannot read the workers' announcements at '{NO_BROKER}'")
    assert "stuck: unknown waiting, 1 failing" in stuck
    assert "postgresql://farm:***@db:5432/undream" in stuck and "attempt 2 of 3; failures 0 of 2" in stuck
    assert SECRET not in res.output


def test_status_asks_the_broker_and_says_which_runs_wait(tmp_path):
    if (reason := redis_up()) is not None:
        service_missing(reason)
    _farm(tmp_path)
    db = free_db()  # nobody consumes there
    env = {"UNDREAM_BLOB_URL": str(tmp_path), "UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}"}
    try:
        res = CliRunner().invoke(main, ["status"], env=env, catch_exceptions=False)
    finally:
        release_db(db)
    assert res.exit_code == 0, res.output
    assert "live queues: none" in res.output and "stuck: 3 waiting, 1 failing" in res.output
    assert f"no live worker on queue {CONTROL_QUEUE}" in res.output
    assert f"no live worker on queue {FRAMES_QUEUE}" in res.output


def test_api_workers_and_the_workers_page_show_stuck_runs(tmp_path):
    ids = _farm(tmp_path)
    settings = load_settings(env={"UNDREAM_BLOB_URL": str(tmp_path), "UNDREAM_BROKER_URL": NO_BROKER,
                                  "UNDREAM_CONNECT_TIMEOUT": "1"})
    app = create_app(settings)
    client = app.test_client()
    body = client.get("/api/workers").get_json()
    stuck = body["stuck"]
    assert body["workers"] and stuck["asked"] and stuck["queues"] is None and "Connection refused" in stuck["broker_error"]
    assert [r["run_id"] for r in stuck["failing"]] == [ids["failing"]]
    assert stuck["failing"][0]["reason"].startswith("RenderError: cannot load scene from postgresql://farm:***@")
    page = client.get("/workers").get_data(as_text=True)
    assert 'id="stuck-table"' in page and f'data-run="{ids["failing"]}" data-state="failing"' in page
    assert "Live queues: unknown (cannot read the workers" in page
    assert SECRET not in page and SECRET not in str(body)
    app.extensions["undream"].close()


def test_the_workers_page_reads_any_number_of_runs_in_the_same_number_of_queries(tmp_path):
    counts = []
    for n in (2, 40):
        blobs = tmp_path / f"farm{n}"
        _farm(blobs, n_queued=n)
        with open_store(None, blobs) as store:  # finished runs with jobs by several workers
            for i in range(n):
                run_id = _run(store, f"done{i}")
                store.transition(run_id, ("queued",), "running")
                store.queue_jobs(run_id, 0, [0, 1])
                store.job_started(run_id, 0, 0, worker=f"node-{i % 3}:1")
                store.set_status(run_id, "done")
        app = create_app(load_settings(env={"UNDREAM_BLOB_URL": str(blobs), "UNDREAM_BROKER_URL": NO_BROKER,
                                            "UNDREAM_CONNECT_TIMEOUT": "1"}))
        client = app.test_client()
        client.get("/api/workers")  # the store opened and warmed once
        with sql_statements() as seen:
            body = client.get("/api/workers").get_json()
        assert {w["worker"] for w in body["workers"]} >= {f"node-{i % 3}:1" for i in range(n)}
        assert body["stuck"]["active"] == n + 2  # farm runs: the queued ones, frames and failing (not the local one)
        counts.append(sum(q.lstrip().upper().startswith("SELECT") for q in seen))
        app.extensions["undream"].close()
    # two for the workers; two counting the active farm runs, the failing jobs and their runs; one for the quiet runs
    # the stall rule looks at (none here are quiet for heal_after: their rows are new)
    assert counts == [7, 7], counts


def test_a_worker_is_live_from_its_announcement_until_it_withdraws_or_its_key_lapses():
    if (reason := redis_up()) is not None:
        service_missing(reason)
    db = free_db()
    try:
        settings = load_settings(env={"UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}"})
        withdraw = announce(settings, "w1@host", QUEUES, beat_s=0.1, ttl_s=1)
        assert live_queues(settings) == {q: ("w1@host",) for q in QUEUES}
        assert probe(settings).queues == {q: ("w1@host",) for q in QUEUES}
        withdraw()
        assert live_queues(settings) == {}
        # killed without a word: its last announcement lapses
        redis_client(db).set(PREFIX + "w2@host", json.dumps({"node": "w2@host", "queues": [CONTROL_QUEUE]}), ex=1)
        assert live_queues(settings) == {CONTROL_QUEUE: ("w2@host",)}
        wait_for(lambda: live_queues(settings) == {}, 5, "the lapsed announcement")
    finally:
        release_db(db)


@pytest.mark.slow
def test_a_live_worker_makes_its_queues_live_and_its_runs_not_waiting(tmp_path):
    if (reason := redis_up()) is not None:
        service_missing(reason)
    farm = Farm(tmp_path)
    try:
        with open_store(None, farm.blobs) as store:
            queued = _run(store, "queued")  # recorded, its start never sent: only the queue matters here
        farm.start_worker()
        consumers = probe(farm.settings())
        assert consumers.known and set(consumers.queues) >= set(QUEUES), consumers
        report = stuck_runs(farm.store, lambda: probe(farm.settings()))
        assert report["n_waiting"] == 0 and report["queues"][CONTROL_QUEUE]
        farm.stop()
        wait_for(lambda: not probe(farm.settings()).queues, 20, "the stopped worker to stop answering")
        report = stuck_runs(farm.store, lambda: probe(farm.settings()))
        assert [r["run_id"] for r in report["waiting"]] == [queued]
    finally:
        farm.stop()
