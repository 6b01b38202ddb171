"""The farm heals its runs (issue 41, "Reliability"): a step whose planning failed is planned by the
callback's retry; `undream status` names stalled runs and why; a stalled run's current work is sent
again with an event line saying so; and workers do it by themselves.

In-process with a real store (SQLite, and PostgreSQL where it runs) for the stages' decisions; the
periodic heal runs through Redis and a real `undream worker` subprocess.
"""
from __future__ import annotations

import datetime as dt
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import service_missing
from farm_support import (
    Farm, farm_inputs, free_db, fresh_postgres, make_scene, make_victim, redis_up, release_db, run_config,
    wait_for, write_yaml,
)
from scheduler import stages
from scheduler.heal import FarmView, StallRule, heal, stall_reason, stalled
from scheduler.local import LocalDispatch, drain
from undream.errors import StoreError
from undream.settings import load_settings
from undream.spec.run import RunConfig
from undream.store import open_store
from undream.store.activity import RunHealth

LOST = "queue_jobs: database error at 'postgresql://u:***@db/x': server closed the connection unexpectedly"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    root = tmp_path_factory.mktemp("farm_heal")
    return {"victim": make_victim(root / "victim"), "scene": make_scene(root / "scene", n_frames=3)}


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request):
    """The run database's URL: SQLite in the blob folder (None), or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        yield None
        return
    url, drop = fresh_postgres()
    yield url
    drop()


def _run(tiny, tmp_path: Path, url: str | None, name: str = "heal"):
    """A recorded run of 3 steps over the 3-frame scene; returns (store, run id, contexts)."""
    from undream.engine.context import build_context

    store = open_store(url, tmp_path / f"blobs-{name}")
    config = RunConfig.from_json(run_config(tiny["scene"], tiny["victim"], name=name))
    ctx = build_context(config, tiny["scene"])
    options = stages.FarmOptions(frames_per_task=2, max_attempts=2, failure_budget=1)
    return store, stages.create(store, config, 3, options, out_dir=str(tmp_path / f"out-{name}")), lambda _: ctx


def _reference(tiny, tmp_path: Path) -> np.ndarray:
    """The final texture of the same run with nothing lost."""
    store, run_id, contexts = _run(tiny, tmp_path, None, "reference")
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    drain(store, contexts, dispatch)
    return store.final_texture(run_id)


# The callback whose planning fails, per phase planned: (phase, k) of the callback; (phase, k) planned
FAILS = {"attack": (("attack", 0), ("attack", 1)), "pre": (("attack", 2), ("pre", 3)),
         "adversarial": (("pre", 3), ("adversarial", 3))}


@pytest.mark.parametrize("planned", list(FAILS))
def test_a_callback_whose_planning_failed_after_its_step_plans_when_retried(tiny, tmp_path, database, planned,
                                                                             monkeypatch):
    """Chaos soak, issue 41: the database dropped between the step (committed) and recording the next
    iteration's jobs; the retried callback found the run past its iteration, said "stale", and the run
    stayed `running` with no job. Now the retry plans what is missing, once."""
    store, run_id, contexts = _run(tiny, tmp_path, database)
    (cb_phase, cb_k), (phase, k) = FAILS[planned]
    claim, failed = store.claim_jobs, []

    def drops_once(run, at, frames, ph, statuses):
        if (ph, at) == (phase, k) and not failed:
            failed.append(ph)
            raise StoreError(LOST)
        return claim(run, at, frames, ph, statuses)

    monkeypatch.setattr(store, "claim_jobs", drops_once)
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    with pytest.raises(StoreError, match="server closed the connection"):
        drain(store, contexts, dispatch)
    run = store.get_run(run_id)
    assert (run.status, run.iteration) == ("running" if planned == "attack" else "evaluating", k)
    assert store.jobs(run_id, k, phase) == [] and not dispatch.queue  # the hang: nothing recorded, nothing sent

    assert stages.collect(store, contexts, run_id, cb_phase, cb_k, dispatch) == "replanned"  # Celery's retry
    assert [(item[2], item[3], sorted(sum(item[4], []))) for item in dispatch.queue] == [(phase, k, [0, 1, 2])]
    assert {j.status for j in store.jobs(run_id, k, phase)} == {"queued"}
    assert stages.collect(store, contexts, run_id, cb_phase, cb_k, dispatch) == "stale"  # a duplicate: nothing twice
    assert len(dispatch.queue) == 1
    drain(store, contexts, dispatch)
    assert store.get_run(run_id).status == "done"
    assert [r.k for r in store.iterations(run_id)] == [0, 1, 2]
    np.testing.assert_array_equal(store.final_texture(run_id), _reference(tiny, tmp_path))


def test_two_callbacks_of_one_iteration_queue_the_next_once(tiny, tmp_path):
    store, run_id, contexts = _run(tiny, tmp_path, None)
    dispatch = LocalDispatch()
    stages.start(store, contexts, run_id, dispatch)
    _, _, phase, k, parts = dispatch.queue.popleft()
    for part in parts:
        stages.run_batch(store, contexts, run_id, phase, k, part)
    assert stages.collect(store, contexts, run_id, "attack", 0, dispatch) == "stepped"
    assert stages.collect(store, contexts, run_id, "attack", 0, dispatch) == "stale"
    assert [item[:4] for item in dispatch.queue] == [("frames", run_id, "attack", 1)]


# -- the stall rule ------------------------------------------------------------------------------

NOW = dt.datetime(2026, 11, 28, 20, 0, tzinfo=dt.timezone.utc)
RULE = StallRule(after_s=600, started_s=600 + 3600)


def _health(status: str = "running", quiet_s: float = 900, unfinished: int = 0, started: int = 0) -> RunHealth:
    then = NOW - dt.timedelta(seconds=quiet_s)
    return RunHealth("r1", "r", status, 4, then, 0, {}, None, unfinished, 0, then if unfinished else None, started)


KNOWN = FarmView(held=frozenset(), waiting=frozenset(), unread=frozenset())  # the broker read: nothing of r1


def test_the_stall_rule_says_why_and_leaves_held_waiting_and_recent_runs_alone():
    assert stall_reason(_health("queued"), NOW, RULE, KNOWN) == \
        "queued, its start not run for 15 min (its message lost)"
    assert stall_reason(_health(), NOW, RULE, KNOWN) == \
        "no job queued or started at k=4 for 15 min (its callback lost, or it found nothing to do)"
    assert stall_reason(_health(unfinished=3), NOW, RULE, KNOWN) == \
        "3 job(s) queued at k=4, none started for 15 min (their messages lost)"
    # a started job no live worker holds (its worker killed or stopped): stalled after heal_after, not an hour
    assert stall_reason(_health(unfinished=3, started=1), NOW, RULE, KNOWN) == \
        "1 job(s) started at k=4, nothing finished for 15 min (no live worker holds them)"
    assert stall_reason(_health(quiet_s=599), NOW, RULE, KNOWN) is None
    assert stall_reason(_health(), NOW, StallRule(0, 0), KNOWN) is None  # heal_after 0: never
    # a live worker holds a task of it: a long job at work, never sent again, however long
    held = FarmView(held=frozenset({"r1"}), waiting=frozenset(), unread=frozenset())
    for quiet in (900, 4300, 86400):
        assert stall_reason(_health(unfinished=3, started=1, quiet_s=quiet), NOW, RULE, held) is None
        assert stall_reason(_health(quiet_s=quiet), NOW, RULE, held) is None  # its callback, running
    # a message of it waits in a queue: behind other runs' work, not lost
    waiting = FarmView(held=frozenset(), waiting=frozenset({"r1"}), unread=frozenset())
    assert stall_reason(_health("queued", quiet_s=86400), NOW, RULE, waiting) is None


def test_where_the_broker_cannot_say_the_stall_rule_falls_back_on_time():
    """Announcements unknown (Redis restarted less than three worker beats ago) or a queue unread: a started job,
    or next work whose queue may hold it, is left alone for visibility_timeout more."""
    blind = FarmView.blind("Redis unreachable")
    assert stall_reason(_health(unfinished=3, started=1), NOW, RULE, blind) is None
    assert stall_reason(_health(unfinished=3, started=1, quiet_s=4300), NOW, RULE, blind) == \
        "1 job(s) started at k=4, nothing finished for 71 min (the broker lost them)"
    assert stall_reason(_health(), NOW, RULE, blind) is None
    assert stall_reason(_health(quiet_s=4300), NOW, RULE, blind) is not None
    unread_jobs = FarmView(held=frozenset(), waiting=frozenset(), unread=frozenset({"jobs"}))
    assert stall_reason(_health(unfinished=3), NOW, RULE, unread_jobs) is None
    assert stall_reason(_health(), NOW, RULE, unread_jobs) is not None  # its callback: the control queue was read
    no_presence = FarmView(held=None, waiting=frozenset(), unread=frozenset())  # who holds what: unknown
    for kind in ({"unfinished": 3, "started": 1}, {"unfinished": 3}, {}, {"status": "queued"}):
        assert stall_reason(_health(**kind), NOW, RULE, no_presence) is None  # a worker may hold it (prefetched)
        assert stall_reason(_health(**kind, quiet_s=4300), NOW, RULE, no_presence) is not None


def _stalled_farm(blobs: Path) -> dict[str, str]:
    """Runs recorded without Mitsuba: one running with no job (``nojob``), one with jobs queued and
    none started (``lost``), one with a job started (``busy``) and one its own process drives (``local``)."""
    with open_store(None, blobs) as store:
        ids = {}
        for name in ("nojob", "lost", "busy", "local"):
            config = RunConfig.from_json({"scene": "s", "name": name, "attack": {"name": "pgd", "steps": 2}})
            ids[name] = store.create_run(config.name, config.to_json(), 3, 0)
            store.transition(ids[name], ("queued",), "running")
        for name in ("lost", "busy", "local"):
            store.queue_jobs(ids[name], 0, [0, 1, 2])
        store.job_started(ids["busy"], 0, 1, worker="node:1")
        assert store.claim(ids["local"], "node:2")
    return ids


def test_runs_waiting_in_a_queue_do_not_hide_a_stalled_run_behind_them(tmp_path):
    """A pass heals at most ``limit`` runs, but it looks past the quiet runs that wait their turn."""
    ids = _stalled_farm(tmp_path)
    waiting = FarmView(held=frozenset(), waiting=frozenset({ids["nojob"], ids["lost"]}), unread=frozenset())
    time.sleep(1.1)
    with open_store(None, tmp_path) as store:
        found = stalled(store, StallRule(after_s=1, started_s=100), limit=1, view=waiting)
    assert [run.id for run, _ in found] == [ids["busy"]]  # the two quieter ones wait in a queue


def test_a_pass_heals_only_the_runs_both_its_looks_find_stalled(tmp_path):
    """A task taken between the looks (its worker announces it within a second) saves its run; the
    runs stalled at both looks are healed, each with its event line; a run its own process drives never."""
    ids = _stalled_farm(tmp_path)
    rule = StallRule(after_s=1, started_s=100)
    taken = FarmView(held=frozenset({ids["nojob"], ids["busy"]}), waiting=frozenset({ids["lost"]}), unread=frozenset())
    time.sleep(1.1)
    with open_store(None, tmp_path) as store:
        dispatch, looks = LocalDispatch(), iter([KNOWN, taken])
        assert heal(store, dispatch, rule, by="node:7", view=lambda: next(looks), confirm_s=0.05) == []
        assert not dispatch.queue and all(store.events(i) == [] for i in ids.values())
        healed = heal(store, dispatch, rule, by="node:7", view=lambda: KNOWN, confirm_s=0.05)
        assert {h["run_id"] for h in healed} == {ids["nojob"], ids["lost"], ids["busy"]}
        assert all(len(store.events(ids[n])) == 1 for n in ("nojob", "lost", "busy"))
        assert store.events(ids["local"]) == []
        # recorded without an attack state (no Mitsuba here): what is sent again is their start
        assert sorted(item[:2] for item in dispatch.queue) == \
            sorted(("start", ids[n]) for n in ("nojob", "lost", "busy"))


def test_the_farm_view_reads_the_queues_across_priorities_and_the_workers_announcements():
    from workers.health import farm_view
    from workers.presence import PRIORITY_SEP, SINCE_KEY, announce, ttl_of
    from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE, QUEUES
    from workers.app import create_celery_app

    if (reason := redis_up()) is not None:
        service_missing(reason)
    db = free_db()
    try:
        settings = load_settings(env={"UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}"})
        assert farm_view(settings) == FarmView(None, frozenset(), frozenset(), farm_view(settings).why)
        app = create_celery_app(settings)  # real task messages, as the farm sends them
        app.signature("undream.frames", args=("run-a", "attack", 2, [0, 1])).apply_async()
        app.signature("undream.collect", args=("run-b", "attack", 2)).apply_async(priority=3)
        app.signature("undream.start", args=("run-c",)).apply_async()
        from farm_support import redis_client

        client = redis_client(db)
        assert client.llen(FRAMES_QUEUE) == 1 and client.llen(f"{CONTROL_QUEUE}{PRIORITY_SEP}3") == 1
        withdraw = announce(settings, "w1@host", QUEUES, holds=lambda: ["run-d", "run-d"])
        try:
            view = farm_view(settings)
            assert view.waiting == {"run-a", "run-b", "run-c"} and view.unread == frozenset()
            assert view.held is None and "announced" in view.why  # the announcements are younger than three beats
            client.set(SINCE_KEY, time.time() - ttl_of(settings) - 1)
            assert farm_view(settings).held == {"run-d"}
        finally:
            withdraw()
        assert farm_view(settings).held == frozenset()
        from workers.presence import queued_runs

        assert queued_runs(settings, QUEUES, limit=1) == (frozenset({"run-a"}), frozenset({CONTROL_QUEUE}))
    finally:
        release_db(db)
    unreachable = load_settings(env={"UNDREAM_BROKER_URL": "redis://127.0.0.1:1/0", "UNDREAM_CONNECT_TIMEOUT": "1"})
    view = farm_view(unreachable)  # unknown: nothing called lost that could be held or waiting
    assert view.held is None and view.unread == {"queued", "callback", "jobs"}


def test_status_names_the_stalled_runs_while_every_queue_has_a_live_worker(tmp_path):
    """Chaos soak, issue 41: `undream status` said "stuck: none" for runs with nothing in flight,
    because every queue had a live worker."""
    from workers.presence import announce
    from workers.queues import QUEUES

    if (reason := redis_up()) is not None:
        service_missing(reason)
    ids = _stalled_farm(tmp_path)
    db = free_db()
    env = {"UNDREAM_BLOB_URL": str(tmp_path), "UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}",
           "UNDREAM_HEAL_AFTER": "1"}
    withdraw = announce(load_settings(env=env), "w1@host", QUEUES, holds=lambda: [ids["busy"]])  # its long job
    from farm_support import redis_client
    from workers.presence import SINCE_KEY

    redis_client(db).set(SINCE_KEY, time.time() - 3600)  # a farm up for an hour: every worker has announced itself
    try:
        time.sleep(1.2)
        from undream.cli import main

        res = CliRunner().invoke(main, ["status"], env=env, catch_exceptions=False)
    finally:
        withdraw()
        release_db(db)
    assert res.exit_code == 0, res.output
    assert "stuck: 0 waiting, 0 failing, 2 stalled" in res.output, res.output
    stuck = res.output.split("stuck:")[1]
    assert ids["nojob"][:8] in stuck and "no job queued or started at k=0" in stuck
    assert ids["lost"][:8] in stuck and "3 job(s) queued at k=0, none started" in stuck
    assert ids["busy"][:8] not in stuck and ids["local"][:8] not in stuck


def test_the_dashboard_shows_stalled_runs_and_a_runs_heals(tmp_path):
    """The workers page lists the stalled runs with the reason; a run's page its event lines."""
    from undream.dashboard import create_app
    from workers.presence import announce
    from workers.queues import QUEUES

    if (reason := redis_up()) is not None:
        service_missing(reason)
    ids = _stalled_farm(tmp_path)
    with open_store(None, tmp_path) as store:
        store.add_event(ids["lost"], "healed: 3 job(s) queued at k=0, none started for 61 s (their messages lost); "
                                     "sent again: its attack jobs without a result, then their callback", "node:7")
    db = free_db()
    env = {"UNDREAM_BLOB_URL": str(tmp_path), "UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}",
           "UNDREAM_HEAL_AFTER": "1"}
    settings = load_settings(env=env)
    withdraw = announce(settings, "w1@host", QUEUES, holds=lambda: [ids["busy"]])
    from farm_support import redis_client
    from workers.presence import SINCE_KEY

    redis_client(db).set(SINCE_KEY, time.time() - 3600)  # a farm up for an hour: every worker has announced itself
    app = create_app(settings)
    try:
        time.sleep(1.2)
        client = app.test_client()
        page = client.get("/workers").get_data(as_text=True)
        run_page = client.get(f"/runs/{ids['lost']}").get_data(as_text=True)
    finally:
        app.extensions["undream"].close()
        withdraw()
        release_db(db)
    assert f'data-run="{ids["nojob"]}" data-state="stalled"' in page
    assert "no job queued or started at k=0" in page and "2 stalled" in page
    assert 'id="run-events"' in run_page and "node:7: healed: 3 job(s) queued at k=0" in run_page


def test_a_stalled_run_is_healed_once_with_an_event_and_finishes(tiny, tmp_path):
    """The iteration's jobs ran; its callback was lost (a restarted broker). The heal sends the work
    without a result (none) and the callback; the run finishes as if nothing happened."""
    store, run_id, contexts = _run(tiny, tmp_path, None)
    dispatch = LocalDispatch()
    stages.start(store, contexts, run_id, dispatch)
    _, _, phase, k, parts = dispatch.queue.popleft()
    for part in parts:
        stages.run_batch(store, contexts, run_id, phase, k, part)  # then the callback is lost
    rule = StallRule(after_s=0.5, started_s=10)
    assert stalled(store, rule) == []  # not quiet for long enough yet
    time.sleep(0.6)
    healed = heal(store, dispatch, rule, by="node:7", view=lambda: KNOWN, confirm_s=0.1)
    assert healed == [{"run_id": run_id, "sent": "attack",
                       "reason": healed[0]["reason"]}] and "no job queued or started at k=0" in healed[0]["reason"]
    assert list(dispatch.queue) == [("frames", run_id, "attack", 0, [])]  # the callback alone: every job succeeded
    (event,) = store.events(run_id)
    assert event.by == "node:7" and event.line.startswith("healed: no job queued or started at k=0")
    assert event.line.endswith("sent again: its attack jobs without a result, then their callback")
    assert heal(store, dispatch, rule, by="node:7", view=lambda: KNOWN) == []  # quiet again only after heal_after
    drain(store, contexts, dispatch)
    assert store.get_run(run_id).status == "done"
    np.testing.assert_array_equal(store.final_texture(run_id), _reference(tiny, tmp_path))


def test_an_announcement_lapses_three_worker_beats_after_the_last():
    """``worker_beat`` sets how often a worker announces itself and when a silent one is gone: the key's
    expiry is three beats, renewed every beat; the announcements are complete three beats after Redis
    started empty."""
    from farm_support import redis_client
    from workers.presence import PREFIX, SINCE_KEY, announce, presence, ttl_of
    from workers.queues import QUEUES

    if (reason := redis_up()) is not None:
        service_missing(reason)
    db = free_db()
    try:
        settings = load_settings(env={"UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}", "UNDREAM_WORKER_BEAT": "1"})
        assert ttl_of(settings) == 3.0 and ttl_of(load_settings(env={})) == 30.0
        client = redis_client(db)
        withdraw = announce(settings, "w1@host", QUEUES)
        try:
            assert 2 <= client.ttl(PREFIX + "w1@host") <= 3
            time.sleep(2.5)  # past two beats: renewed, never lapsed
            assert client.ttl(PREFIX + "w1@host") >= 2 and presence(settings).queues
            since = float(client.get(SINCE_KEY))
            assert not presence(settings, now=since + 2.9).complete and presence(settings, now=since + 3.01).complete
        finally:
            withdraw()
        assert client.get(PREFIX + "w1@host") is None
    finally:
        release_db(db)


# -- workers heal by themselves ------------------------------------------------------------------


@pytest.fixture(scope="module")
def farm_tiny(tmp_path_factory, mi):
    return farm_inputs(tmp_path_factory, "farm_heal_int", 4)


@pytest.mark.slow
def test_a_worker_heals_a_run_whose_broker_lost_everything(farm_tiny):
    """Chaos soak, issue 41: the worker is SIGKILLed mid-run and the broker's database emptied (a
    restarted Redis without persistence): the run stays `running` with nothing in flight. A new
    worker, left alone, finds it stalled, sends its current work again with an event line saying
    so, and the run ends with the undisturbed run's texture."""
    from scheduler.local import run_local

    # a worker beat of 2 s: the new worker's announcements are complete after 6 s instead of 30 s
    farm = Farm(farm_tiny["root"] / "heal", heal_after=4, heal_interval=1, worker_beat=2)
    farm.root.mkdir()
    # 16 steps: a loaded machine's polling loop (it shares the cores with the worker) must still find
    # the run mid-way; with 6 it once first saw the run after its last step
    cfg = run_config(farm_tiny["scene"], farm_tiny["victim"], name="healed", steps=16, sim_spp=128, grad_spp=16)
    try:
        first = farm.start_worker()
        run_id = farm.submit(write_yaml(farm.root / "healed.yaml", cfg))
        wait_for(lambda: farm.store.get_run(run_id).iteration >= 1, 90, "the run to step", interval=0.02)
        farm.kill_worker(first)
        from farm_support import redis_client

        redis_client(farm.db).flushdb()  # the broker's queues, unacked jobs and chord counters: gone
        at_kill = farm.store.get_run(run_id)
        assert at_kill.status in ("running", "evaluating") and at_kill.iteration < 16
        farm.start_worker()
        run = farm.wait_status(run_id, timeout=150)
        events = farm.store.events(run_id)
        assert events and all(e.line.startswith("healed: ") and e.by.startswith("undream worker ") for e in events)
        assert [r.k for r in farm.store.iterations(run_id)] == list(range(16)) and run.failures == 0
        run_local(RunConfig.from_json(cfg), farm.root / "reference", progress=False)
        out = Path(run.out_dir) if run.out_dir else farm.blobs / "outputs" / f"{run.name}-{run_id[:8]}"
        np.testing.assert_array_equal(np.load(out / "texture_final.npy"),
                                      np.load(farm.root / "reference" / "texture_final.npy"))
        res = farm.cli("status", run_id)
        assert res.returncode == 0 and "events:" in res.stdout and "healed: " in res.stdout, res.stdout
    finally:
        farm.stop()


def _started_job(farm: Farm, run_id: str):
    """A started frame job of iteration >= 1 of the run, with a worker, else None (for wait_for)."""
    run = farm.store.get_run(run_id)
    jobs = [j for j in farm.store.jobs(run_id, run.iteration) if j.status == "started" and j.worker]
    return run.iteration >= 1 and jobs and jobs[0]


def _final(farm: Farm, run) -> np.ndarray:
    out = Path(run.out_dir) if run.out_dir else farm.blobs / "outputs" / f"{run.name}-{run.id[:8]}"
    return np.load(out / "texture_final.npy")


@pytest.mark.slow
def test_a_killed_workers_job_is_sent_again_by_the_healer_not_after_the_visibility_timeout(farm_tiny):
    """Issue 41: with the default visibility timeout a SIGKILLed worker's job came back after an hour.
    Now its announcement lapses (three worker beats: 30 s by default, 6 s here), nothing else holds
    the run, and the healer sends the job again: the run finishes with the undisturbed run's
    texture, no person involved, the broker's copy of the job still an hour away."""
    from scheduler.local import run_local
    from workers.presence import ttl_of

    farm = Farm(farm_tiny["root"] / "killed", heal_after=3, heal_interval=1, visibility_timeout=3600,
                frames_per_task=1, worker_beat=2)
    farm.root.mkdir()
    cfg = run_config(farm_tiny["scene"], farm_tiny["victim"], name="killed", steps=4, sim_spp=256, grad_spp=16)
    try:
        run_id = farm.submit(write_yaml(farm.root / "killed.yaml", cfg))
        workers = [farm.start_worker(), farm.start_worker()]
        job = wait_for(lambda: _started_job(farm, run_id), 90, "a started frame job of iteration >= 1",
                       interval=0.005)
        victim = next(w for w in workers if w.pid == os.getpgid(int(job.worker.split(":")[1])))
        farm.kill_worker(victim)
        killed = time.monotonic()
        run = farm.wait_status(run_id, timeout=90)
        took = time.monotonic() - killed
        # the announcement's lapse, heal_after, a pass interval, the confirming look, the rest of the run
        assert took < ttl_of(farm.settings()) + 3 + 1 + 2 + 25, took
        again = next(j for j in farm.store.jobs(run_id, job.k) if j.frame == job.frame)
        assert again.status == "succeeded" and again.attempts == 2 and run.failures == 0  # attempts kept
        healed = [e.line for e in farm.store.events(run_id)]
        assert any(line.startswith(f"healed: 1 job(s) started at k={job.k}") and "no live worker holds them" in line
                   for line in healed), healed
        assert [r.k for r in farm.store.iterations(run_id)] == [0, 1, 2, 3]
        run_local(RunConfig.from_json(cfg), farm.root / "reference", progress=False)
        np.testing.assert_array_equal(_final(farm, run), np.load(farm.root / "reference" / "texture_final.npy"))
    finally:
        farm.stop()


@pytest.mark.slow
def test_a_long_job_is_never_sent_again_while_its_worker_lives(farm_tiny):
    """A job that makes no progress for 5x heal_after (its pool process stopped, its worker alive and
    announcing it) is left alone: no heal, no second attempt; the run finishes once it goes on."""
    import signal

    from farm_support import redis_client
    from workers.health import farm_view
    from workers.presence import SINCE_KEY

    farm = Farm(farm_tiny["root"] / "long", heal_after=2, heal_interval=1, frames_per_task=1,
                visibility_timeout=3600)
    farm.root.mkdir()
    cfg = run_config(farm_tiny["scene"], farm_tiny["victim"], name="long", steps=3, sim_spp=256, grad_spp=16)
    try:
        run_id = farm.submit(write_yaml(farm.root / "long.yaml", cfg))
        farm.start_worker()
        redis_client(farm.db).set(SINCE_KEY, time.time() - 3600)  # a farm up for an hour: announcements complete
        job = wait_for(lambda: _started_job(farm, run_id), 90, "a started frame job of iteration >= 1",
                       interval=0.005)
        child = int(job.worker.split(":")[1])
        os.kill(child, signal.SIGSTOP)  # the job "runs" on: no progress at all
        try:
            time.sleep(3)
            assert farm_view(farm.settings()).held == {run_id}  # what keeps it: its worker says it holds it
            time.sleep(7)
            assert farm.store.events(run_id) == []
            res = farm.cli("status")
            assert res.returncode == 0 and "stalled" not in res.stdout.split("stuck:")[-1], res.stdout
        finally:
            os.kill(child, signal.SIGCONT)
        run = farm.wait_status(run_id, timeout=90)
        assert farm.store.events(run_id) == []
        assert next(j for j in farm.store.jobs(run_id, job.k) if j.frame == job.frame).attempts == 1
        assert run.failures == 0
    finally:
        farm.stop()


# -- a worker's database ---------------------------------------------------------------------------


def _settings(blobs: Path, database: str | None):
    env = {"UNDREAM_BLOB_URL": str(blobs), "UNDREAM_CACHE_DIR": str(blobs.parent / "cache")}
    return load_settings(env={**env, "UNDREAM_DATABASE_URL": database} if database else env)


def test_a_worker_refuses_a_database_that_is_not_the_farms_and_creates_nothing(tmp_path):
    """Chaos soak, issue 41: a worker pointed at `sqlite:///elsewhere.db` made that file and took a real
    run's start message. Where the farm's blob store holds its runs' packed scenes, a database without
    the farm's tables is refused, in one line, and not created; a new farm's database is made as before."""
    from workers.startup import NotTheFarm, farm_store

    blobs, elsewhere = tmp_path / "blobs", tmp_path / "elsewhere.db"
    with farm_store(_settings(blobs, None)) as store:  # a new farm: the default SQLite file is made
        assert store.runs() == [] and (blobs / "undream.db").is_file()
    (blobs / "scenes").mkdir()
    (blobs / "scenes" / f"{'0' * 64}.tar").write_bytes(b"a run's scene")
    with pytest.raises(NotTheFarm) as refused:
        farm_store(_settings(blobs, f"sqlite:///{elsewhere}"))
    assert str(refused.value) == (
        f"database_url 'sqlite:///{elsewhere}': not the farm's database (none of the farm's tables, while "
        f"blob_url '{blobs}' holds 1 packed scene(s) of its runs); give the farm's --database "
        "(UNDREAM_DATABASE_URL); nothing was created")
    assert not elsewhere.exists()
    with farm_store(_settings(blobs, None)) as store:  # the farm's own database: opened
        assert store.runs() == []


@pytest.mark.slow
def test_undream_worker_on_another_database_exits_in_one_line(tmp_path):
    if (reason := redis_up()) is not None:
        service_missing(reason)
    farm = Farm(tmp_path)
    try:
        (farm.blobs / "scenes").mkdir(parents=True)
        (farm.blobs / "scenes" / f"{'1' * 64}.tar").write_bytes(b"a run's scene")
        farm.env["UNDREAM_DATABASE_URL"] = f"sqlite:///{tmp_path / 'elsewhere.db'}"
        res = farm.cli("worker", timeout=60)
        assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
        assert "not the farm's database" in res.stderr and not (tmp_path / "elsewhere.db").exists()
    finally:
        farm.stop()


def test_a_worker_waits_for_a_database_that_does_not_answer(tmp_path):
    from workers.startup import wait_for_store

    settings = _settings(tmp_path / "blobs", "postgresql://alice:s3cret@127.0.0.1:1/farm")
    lines, waits = [], []

    class Enough(Exception):
        pass

    def sleep(seconds: float) -> None:
        waits.append(seconds)
        if len(waits) == 7:
            raise Enough

    with pytest.raises(Enough):
        wait_for_store(settings, lines.append, sleep)
    assert waits == [1, 2, 4, 8, 16, 30, 30]
    assert lines[0].startswith("undream worker: waiting for the run database: cannot reach the run database at "
                               "'postgresql://alice:***@127.0.0.1:1/farm'") and lines[0].endswith("trying again in 1 s")
    assert not any("s3cret" in line for line in lines)
