"""The farm's logic without a broker: settings, scenes in the blob store, stages, Celery in eager mode.

Eager mode never serializes and raises differently (docs/architecture.md):
these tests check the stages' decisions; tests/test_farm_integration.py runs
the same through Redis and real worker processes.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from types import SimpleNamespace
from pathlib import Path

import numpy as np
import pytest

from farm_support import make_scene, make_victim, run_config, write_yaml
from scheduler import stages
from scheduler.iteration import MissingResults, reduce_and_step
from scheduler.local import LocalDispatch, RunFailed, drain, run_local
from scheduler.scenes import pack_scene, store_scene, unpack_scene
from undream.errors import SpecError, StoreError
from undream.settings import SettingsError, load_settings
from undream.spec.run import RunConfig
from undream.store import open_store

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    root = tmp_path_factory.mktemp("farm_logic")
    return {"victim": make_victim(root / "victim"), "scene": make_scene(root / "scene", n_frames=3)}


def _config(tiny, **kw) -> RunConfig:
    return RunConfig.from_json(run_config(tiny["scene"], tiny["victim"], **kw))


def _local_run(tiny, tmp_path, cfg, options=None):
    """A run through the stages in this process; returns (store, run id, context)."""
    from undream.engine.context import build_context

    store = open_store(None, tmp_path / "store")
    ctx = build_context(cfg, tiny["scene"])
    opts = options or stages.FarmOptions(frames_per_task=2, max_attempts=2, failure_budget=1)
    run_id = stages.create(store, cfg, 3, opts, out_dir=str(tmp_path / "out"))
    return store, run_id, ctx


# -- settings ---------------------------------------------------------------------------------


def test_settings_precedence_and_errors_name_their_source(tmp_path):
    path = write_yaml(tmp_path / "farm.yaml", {"broker_url": "redis://file:6379/1", "concurrency": 3,
                                               "blob_url": "/srv/blobs"})
    s = load_settings(path, env={"UNDREAM_CONCURRENCY": "4", "UNDREAM_DRJIT_THREADS": "2"},
                      blob_url="/flag/blobs")
    assert (s.broker_url, s.concurrency, s.drjit_threads, s.blob_url) == \
        ("redis://file:6379/1", 4, 2, "/flag/blobs")
    assert s.backend_url == s.broker_url and load_settings(env={}).broker_url == "redis://127.0.0.1:6379/0"
    assert load_settings(env={"UNDREAM_SETTINGS": str(path)}).concurrency == 3
    with pytest.raises(SettingsError, match="UNDREAM_CONCURRENCY: must be an integer, got 'many'"):
        load_settings(env={"UNDREAM_CONCURRENCY": "many"})
    with pytest.raises(SettingsError, match="UNDREAM_FAILURE_BUDGET: must be an integer >= 0, got -1"):
        load_settings(env={"UNDREAM_FAILURE_BUDGET": "-1"})
    with pytest.raises(SettingsError, match="UNDREAM_WORKER_BEAT: must be an integer >= 1, got 0"):
        load_settings(env={"UNDREAM_WORKER_BEAT": "0"})
    with pytest.raises(SettingsError, match=r"farm.yaml: brokr_url: unknown setting"):
        load_settings(write_yaml(tmp_path / "farm.yaml", {"brokr_url": "x"}), env={})
    with pytest.raises(SettingsError, match="--concurrency: must be an integer >= 1, got 0"):
        load_settings(env={}, concurrency=0)
    with pytest.raises(SettingsError, match=r"UNDREAM_RESULT_BACKEND: rpc:// cannot hold the chords"):
        load_settings(env={"UNDREAM_RESULT_BACKEND": "rpc://"})


def test_frames_per_task_is_one_task_per_slot_unless_set():
    s = load_settings(env={})
    assert [s.frames_per_task_for(n) for n in (1, 2, 7, 8)] == [1, 1, 4, 4]
    assert load_settings(env={"UNDREAM_FARM_SLOTS": "8"}).frames_per_task_for(8) == 1
    assert load_settings(env={"UNDREAM_FRAMES_PER_TASK": "3"}).frames_per_task_for(8) == 3


# -- scenes in the blob store ---------------------------------------------------------------


def test_scene_is_packed_deterministically_and_unpacked_once(tiny, tmp_path):
    a, b = pack_scene(tiny["scene"], tmp_path / "a.tar"), pack_scene(tiny["scene"], tmp_path / "b.tar")
    assert a == b and (tmp_path / "a.tar").read_bytes() == (tmp_path / "b.tar").read_bytes()
    store = open_store(None, tmp_path / "blobs")
    key = store_scene(store.blobs, tiny["scene"])
    assert key == f"scenes/{a}.tar" and store_scene(store.blobs, tiny["scene"]) == key
    assert len(list((tmp_path / "blobs" / "scenes").iterdir())) == 1
    dirs: list[Path] = []
    threads = [threading.Thread(target=lambda: dirs.append(unpack_scene(store.blobs, key, tmp_path / "c")))
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(dirs)) == 1 and len(dirs) == 4
    for f in tiny["scene"].rglob("*"):
        if f.is_file():
            assert (dirs[0] / f.relative_to(tiny["scene"])).read_bytes() == f.read_bytes()
    assert [p.name for p in (tmp_path / "c" / "scenes").iterdir()] == [a]  # no temporary leftovers
    with open(store.blobs.path(key), "r+b") as f:
        f.seek(600)
        f.write(b"corrupt")
    with pytest.raises(StoreError, match="does not match its SHA-256"):
        unpack_scene(store.blobs, key, tmp_path / "d")


# -- stages ------------------------------------------------------------------------------------


def test_reduce_refuses_to_step_while_a_job_has_no_result(tiny, tmp_path):
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    dispatch = LocalDispatch()
    stages.start(store, lambda _: ctx, run_id, dispatch)
    assert dispatch.queue.popleft() == ("frames", run_id, "attack", 0, [[0, 1], [2]])
    stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0, 1])
    with pytest.raises(MissingResults, match="no result yet for frame"):
        reduce_and_step(store, ctx.attack, run_id, 0)
    assert stages.collect(store, lambda _: ctx, run_id, "attack", 0, dispatch) == "rerun"
    assert list(dispatch.queue) == [("frames", run_id, "attack", 0, [[2]])]  # only the missing frame
    assert store.get_run(run_id).iteration == 0
    drain(store, lambda _: ctx, dispatch)
    assert store.get_run(run_id).status == "done"
    assert [r.k for r in store.iterations(run_id)] == [0, 1, 2]


def _failing(frames, exc=RuntimeError("the GPU fell off")):
    from undream.engine import job

    real = job.render_and_grad_many

    def fake(ctx, positions, texture, iteration):
        if set(positions) & set(frames):
            raise exc
        return real(ctx, positions, texture, iteration)
    return fake


def test_a_failing_job_is_retried_then_counted_against_the_budget(tiny, tmp_path, monkeypatch):
    from undream.engine import job

    monkeypatch.setattr(job, "render_and_grad_many", _failing({1}))
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    drain(store, lambda _: ctx, dispatch)
    run = store.get_run(run_id)
    assert run.status == "failed" and run.iteration == 0 and run.failures == 2
    # frames 0 and 1 are one task (frames_per_task 2), computed together: frame 1's error is both's
    assert "frame(s) 0, 1 failed" in run.error and "the GPU fell off" in run.error
    assert "failure budget of 1 used up" in run.error
    jobs = {j.frame: j for j in store.jobs(run_id, 0)}
    assert jobs[1].status == "queued" and "RuntimeError: the GPU fell off" in jobs[1].error
    assert store.iterations(run_id) == []  # never stepped on fewer frames


def test_cancel_stops_a_run_and_resume_finishes_it(tiny, tmp_path):
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    dispatch = LocalDispatch()
    stages.start(store, lambda _: ctx, run_id, dispatch)
    stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0, 1, 2])
    assert stages.cancel(store, run_id)
    assert stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0])["skipped"] == [0]
    assert stages.collect(store, lambda _: ctx, run_id, "attack", 0, dispatch) == "stale"
    assert not reduce_and_step(store, ctx.attack, run_id, 0)
    assert not store.advance(run_id, 0, store.texture(run_id, 0), {}, {})  # a cancelled run never advances
    assert store.get_run(run_id).iteration == 0
    assert stages.cancel(store, run_id) is False  # already cancelled
    fresh = LocalDispatch()
    assert stages.resume(store, run_id, fresh) == "attack"
    assert list(fresh.queue) == [("frames", run_id, "attack", 0, [])]  # every job of k=0 already done
    drain(store, lambda _: ctx, fresh)
    assert store.get_run(run_id).status == "done"


def test_resume_after_a_crash_gives_the_same_texture(tiny, tmp_path):
    cfg = _config(tiny)
    ref_store, ref_id, ctx = _local_run(tiny, tmp_path / "ref", cfg)
    ref = LocalDispatch()
    ref.start(ref_id)
    drain(ref_store, lambda _: ctx, ref)

    store, run_id, _ = _local_run(tiny, tmp_path / "crash", cfg)
    dispatch = LocalDispatch()
    stages.start(store, lambda _: ctx, run_id, dispatch)
    _, _, _, _, batches = dispatch.queue.popleft()  # iteration 0 whole
    for batch in batches:
        stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, batch)
    stages.collect(store, lambda _: ctx, run_id, "attack", 0, dispatch)
    _, _, _, k, batches = dispatch.queue.popleft()  # half of iteration 1, then the process "dies"
    stages.run_batch(store, lambda _: ctx, run_id, "attack", k, batches[0])
    assert store.get_run(run_id).iteration == 1 == k
    fresh = LocalDispatch()
    assert stages.resume(store, run_id, fresh) == "attack"
    assert list(fresh.queue) == [("frames", run_id, "attack", 1, [[2]])]
    drain(store, lambda _: ctx, fresh)
    assert store.get_run(run_id).status == "done"
    assert [r.k for r in store.iterations(run_id)] == [0, 1, 2]
    assert np.array_equal(store.final_texture(run_id), ref_store.final_texture(ref_id))
    for k in range(4):
        assert np.array_equal(store.texture(run_id, k), ref_store.texture(ref_id, k))


class _Killed(BaseException):
    """A SIGKILL, as far as the callback in this process can tell."""


def test_a_callback_killed_while_writing_outputs_is_finished_by_its_redelivery(tiny, tmp_path, monkeypatch):
    """CI, 2026-11-26: the final callback of a sweep's run died after writing part of its output folder
    (the texture, some frames) and before metadata.json, the file that says whose folder it is; every
    retry then took the folder for a user's files and the run failed after 10 retries. The owner is now
    written first, so the redelivered callback finishes the folder."""
    from scheduler import outputs

    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    saves = {"n": 0}
    write = outputs.atomic_write

    def dies_on_the_second_frame(path, data, **kwargs):  # frames are written whole, one file at a time
        if path.suffix == ".png" and path.parent.name.startswith("frames_"):
            saves["n"] += 1
            if saves["n"] == 2:
                raise _Killed()
        return write(path, data, **kwargs)

    monkeypatch.setattr(outputs, "atomic_write", dies_on_the_second_frame)
    with pytest.raises(_Killed):
        drain(store, lambda _: ctx, dispatch)
    out = tmp_path / "out"
    assert (out / "texture_final.png").is_file() and not (out / "results.json").exists()
    assert store.get_run(run_id).status == "evaluating"
    redelivered = LocalDispatch()
    redelivered.queue.append(("frames", run_id, "adversarial", 3, []))  # the callback again, its jobs done
    drain(store, lambda _: ctx, redelivered)
    assert store.get_run(run_id).status == "done"
    assert json.loads((out / "metadata.json").read_text())["run_id"] == run_id
    assert json.loads((out / "results.json").read_text()) == store.get_run(run_id).results
    assert len(list((out / "frames_adversarial").glob("*.png"))) == 3 == len(list((out / "frames_benign").glob("*.png")))


def test_attack_state_keeps_scalars_in_json_and_arrays_once(tiny, tmp_path):
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny, attack={"name": "apgd"}))
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    drain(store, lambda _: ctx, dispatch)
    texts = [store.blobs.path(f"runs/{run_id}/attack_state/{k:06d}.json").read_text() for k in range(4)]
    docs = [json.loads(t) for t in texts]
    for text, doc in zip(texts, docs):
        assert set(doc["T0"]) == {"array"} and set(doc["x_best"]) == {"array"}
        assert len(text) < 2000  # scalars only: one 8×16×3 texture as floats would be ~8 kB
    assert len({doc["T0"]["array"] for doc in docs}) == 1  # T0 written once
    state = store.attack_state(run_id, 3)
    assert state["T0"].shape == (8, 16, 3) and state["visible"].dtype == bool


def test_a_crashed_job_fails_the_local_run_with_its_error(tiny, tmp_path, monkeypatch):
    from undream.engine import job

    monkeypatch.setattr(job, "render_and_grad_many", _failing({0}, ValueError("bad frame")))
    with pytest.raises(RunFailed, match="ValueError: bad frame"):
        run_local(_config(tiny), tmp_path / "out", progress=False)
    (run,) = open_store(None, tmp_path / "out" / "store").runs()
    assert run.status == "failed" and "ValueError: bad frame" in run.error


# -- Celery in eager mode --------------------------------------------------------------------


@pytest.fixture(scope="module")
def eager(tiny, tmp_path_factory):
    """One run through the Celery app in eager mode; every task call and its result recorded."""
    from celery import signals

    from scheduler.submit import Validator, record
    from workers.app import create_celery_app
    from workers.dispatch import CeleryDispatch

    root = tmp_path_factory.mktemp("eager")
    settings = load_settings(env={}, broker_url="memory://", result_backend="cache+memory://",
                             blob_url=str(root / "blobs"), cache_dir=str(root / "cache"))
    app = create_celery_app(settings)
    app.conf.task_always_eager = True
    app.conf.task_eager_propagates = True
    calls: list[tuple[str, list, object]] = []
    args: dict[str, list] = {}

    def pre(task_id=None, task=None, args=None, **_):
        args_by_id[task_id] = list(args)

    def post(task_id=None, task=None, retval=None, **_):
        calls.append((task.name, args_by_id.pop(task_id), retval))

    args_by_id = args
    signals.task_prerun.connect(pre, weak=False)
    signals.task_postrun.connect(post, weak=False)
    try:
        store = open_store(settings.database_url, settings.blob_url)
        prepared = Validator(root / "work")(_config(tiny, name="eager"), Path("."))
        (run_id,) = record(store, [prepared], settings, root / "out")
        CeleryDispatch(app).start(run_id)
    finally:
        signals.task_prerun.disconnect(pre)
        signals.task_postrun.disconnect(post)
    return {"store": store, "run_id": run_id, "calls": calls, "out": root / "out", "app": app}


def test_eager_run_gives_the_local_runs_texture(eager, tiny, tmp_path):
    run = eager["store"].get_run(eager["run_id"])
    assert run.status == "done", run.error
    for name in ("texture_final.png", "texture_final.npy", "results.json", "loss.png", "metadata.json"):
        assert (eager["out"] / name).is_file(), name
    assert len(list((eager["out"] / "frames_adversarial").glob("*.png"))) == 3
    local = run_local(_config(tiny, name="eager"), tmp_path / "local", progress=False)
    assert np.array_equal(np.load(eager["out"] / "texture_final.npy"),
                          np.load(tmp_path / "local" / "texture_final.npy"))
    assert run.results["loss_per_iteration"] == pytest.approx(local["loss_per_iteration"], rel=1e-5)
    assert run.results["benign"] == local["benign"] and run.results["adversarial"] == local["adversarial"]


def test_every_task_argument_and_result_survives_json(eager):
    from workers.healer import HEAL_TASK
    from workers.tasks import TASK_NAMES

    assert {name for name, _, _ in eager["calls"]} == set(TASK_NAMES) == \
        {t for t in eager["app"].tasks if t.startswith("undream.")} - {HEAL_TASK}  # a run's tasks
    for name, args, result in eager["calls"]:
        assert json.loads(json.dumps(args)) == args, name
        assert json.loads(json.dumps(result)) == result, (name, result)
        assert isinstance(result, dict) and result["run_id"] == eager["run_id"]


def test_the_worker_parent_imports_no_renderer():
    code = ("import sys\n"
            "from undream.settings import load_settings\n"
            "from workers.app import create_celery_app\n"
            "from workers.main import worker_argv\n"
            "import undream.cli.farm, scheduler.stages, workers.runtime\n"
            "s = load_settings(env={})\n"
            "create_celery_app(s); worker_argv(s)\n"
            "heavy = [m for m in ('mitsuba', 'drjit', 'torch') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    subprocess.run([sys.executable, "-c", code], check=True)


# -- sweeps and the schema ---------------------------------------------------------------------


def test_sweep_expands_a_grid_and_names_bad_fields(tiny, tmp_path):
    from scheduler.sweep import load_sweep

    base = write_yaml(tmp_path / "run.yaml", run_config(tiny["scene"], tiny["victim"]))
    sweep = load_sweep(write_yaml(tmp_path / "s.yaml", {"name": "grid", "run": "run.yaml",
                                                        "grid": {"attack.eps": [8, 16], "seed": [0, 1, 2]}}))
    assert [r.config.name for r in sweep.runs] == [f"grid-{i:03d}" for i in range(6)]
    assert [(r.config.attack.eps, r.config.seed) for r in sweep.runs] == \
        [(8, 0), (8, 1), (8, 2), (16, 0), (16, 1), (16, 2)]
    assert sweep.runs[0].config.attack.steps == 3 and sweep.runs[0].base_dir == base.parent
    with pytest.raises(SpecError, match=r"s2.yaml: grid.epsilon: not a run-config field"):
        load_sweep(write_yaml(tmp_path / "s2.yaml", {"name": "g", "run": "run.yaml", "grid": {"epsilon": [1]}}))
    with pytest.raises(SpecError, match=r"s3.yaml: run 1 \(loss='hinge'\): loss"):
        load_sweep(write_yaml(tmp_path / "s3.yaml", {"name": "g", "run": "run.yaml",
                                                     "grid": {"loss": ["ce", "hinge"]}}))


def test_a_store_of_another_schema_version_is_refused(tmp_path):
    from sqlalchemy import text

    store = open_store(None, tmp_path)
    with store.engine.begin() as conn:
        conn.execute(text("DELETE FROM undream_schema"))
        conn.execute(text("INSERT INTO undream_schema (version) VALUES (1)"))
    store.close()
    with pytest.raises(StoreError, match=r"has schema version 1, this undream needs version 5 "
                                         r"and cannot upgrade from 1"):
        open_store(None, tmp_path)
    store = open_store(None, tmp_path / "newer")
    with store.engine.begin() as conn:
        conn.execute(text("INSERT INTO undream_schema (version) VALUES (99)"))
    store.close()
    with pytest.raises(StoreError, match=r"has schema version 99, newer than this undream's 5"):
        open_store(None, tmp_path / "newer")


def test_each_app_has_its_own_tasks():
    """Tasks are not Celery 'shared' tasks: a second app (tests, the benchmark) never runs the first's."""
    from workers.app import create_celery_app

    a, b = (create_celery_app(load_settings(env={})) for _ in range(2))
    for name in ("undream.start", "undream.frames", "undream.collect"):
        assert a.tasks[name] is not b.tasks[name] and a.tasks[name].app is a and b.tasks[name].app is b


def test_the_app_sends_task_events_for_flower():
    """Workers send task events and clients a task-sent event, so Flower sees every task of the farm."""
    from workers.app import create_celery_app

    app = create_celery_app(load_settings(env={}))
    assert app.conf.worker_send_task_events is True and app.conf.task_send_sent_event is True
    assert app.conf.event_serializer == "json"


def test_the_example_sweep_expands():
    from farm_support import ROOT
    from scheduler.sweep import load_sweep

    sweep = load_sweep(ROOT / "examples" / "sweeps" / "bin_park_eps.yaml")
    assert len(sweep.runs) == 6 and {r.config.attack.eps for r in sweep.runs} == {16, 32, 64}
    assert all((r.base_dir / r.config.scene).is_file() for r in sweep.runs)


def test_a_process_reads_each_texture_version_once(tiny, tmp_path):
    from undream.lru import LRU

    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    stages.start(store, lambda _: ctx, run_id, LocalDispatch())
    cache: LRU = LRU(stages.TEXTURE_VERSIONS)
    first = stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0, 1], cache)
    second = stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [2], cache)
    texture_bytes = store.blobs.path(f"runs/{run_id}/texture/000000.npy").stat().st_size
    assert first["bytes_read"] == texture_bytes and second["bytes_read"] == 0
    assert first["bytes_written"] > 0 and first["done"] == [0, 1] and second["done"] == [2]


def test_the_planner_sends_the_frames_it_computed_last_last(tiny, tmp_path):
    """The process that closes an iteration plans the next, and the waiting workers take its first
    batches: the batch holding the planner's own last frames goes out last, so that it comes back
    to the process whose scenes and transports hold them."""
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    dispatch = LocalDispatch()
    stages.start(store, lambda _: ctx, run_id, dispatch)
    _, _, _, k, planned = [w for w in dispatch.queue if w[0] == "frames"][-1]
    assert planned == [[0, 1], [2]] and k == 0  # nothing computed here yet: the batches in order
    stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [2])
    stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0, 1])  # this process computed 0 and 1 last
    dispatch.queue.clear()
    assert stages.collect(store, lambda _: ctx, run_id, "attack", 0, dispatch) == "stepped"
    (_, _, phase, k, planned), = [w for w in dispatch.queue if w[0] == "frames"]
    assert (phase, k, planned) == ("attack", 1, [[2], [0, 1]])
    assert stages.served_last("another run", [[0, 1], [2]]) == [[0, 1], [2]]


def test_each_attack_job_keeps_the_victims_prediction_small(tiny, tmp_path):
    """The row of every attack job holds the classifier's verdict on the frame it rendered."""
    store, run_id, ctx = _local_run(tiny, tmp_path, _config(tiny))
    stages.start(store, lambda _: ctx, run_id, LocalDispatch())
    stages.run_batch(store, lambda _: ctx, run_id, "attack", 0, [0, 1, 2])
    jobs = store.jobs(run_id, 0)
    assert [j.frame for j in jobs] == [0, 1, 2]
    for job in jobs:
        pred = job.result["prediction"]
        assert set(pred) == {"label", "score", "correct"} and 0.0 <= pred["score"] <= 1.0
        assert pred["correct"] is (pred["label"] == ctx.targets[job.frame].label)
        assert len(json.dumps(job.result)) < 100


def test_a_detectors_prediction_is_kept_as_detected_and_top_score():
    """A detector's boxes stay out of the job's result: whether the object was found, the top score."""
    from types import SimpleNamespace

    import torch

    from undream.engine.job import prediction_record
    from undream.victims.base import DetPrediction, Target

    ctx = SimpleNamespace(victim=SimpleNamespace(task="detection"),
                          targets=[Target(label=2, box=(10.0, 10.0, 30.0, 30.0)), Target(label=2, box=None)])
    boxes = torch.tensor([[11.0, 9.0, 31.0, 29.0], [0.0, 0.0, 5.0, 5.0]] * 20)
    pred = DetPrediction(boxes, torch.linspace(0.9, 0.1, 40), torch.tensor([2, 7] * 20))
    assert prediction_record(ctx, 0, pred) == {"detected": True, "n_detections": 40, "score": 0.9}
    assert prediction_record(ctx, 1, pred)["detected"] is False
    missed = DetPrediction(boxes[1::2], torch.linspace(0.5, 0.1, 20), torch.full((20,), 7))
    assert prediction_record(ctx, 0, missed) == {"detected": False, "n_detections": 20, "score": 0.5}
    empty = DetPrediction(torch.zeros((0, 4)), torch.zeros(0), torch.zeros(0, dtype=torch.long))
    assert prediction_record(ctx, 0, empty) == {"detected": False, "n_detections": 0, "score": 0.0}


def test_a_stage_that_crashes_on_a_worker_fails_the_run(eager, tiny, tmp_path):
    """Not left evaluating for ever: here the output folder cannot be made (a file is in the way)."""
    from scheduler.submit import Validator, record
    from workers.dispatch import CeleryDispatch

    (tmp_path / "blocker").write_text("a file, not a folder")
    prepared = Validator(tmp_path / "work")(_config(tiny, name="crash"), Path("."))
    (run_id,) = record(eager["store"], [prepared], eager["app"].undream_settings, tmp_path / "blocker" / "out")
    CeleryDispatch(eager["app"]).start(run_id)
    run = eager["store"].get_run(run_id)
    assert run.status == "failed" and run.iteration == 3 and "NotADirectoryError" in run.error


def test_tasks_split_an_iterations_frames_evenly_over_the_slots():
    """The main job's 24 frames hold 6 out: its 18 attacked frames make two tasks of 9 on two slots
    (sized by the 24 frames they were 12 and 6, and the second worker waited on the first)."""
    from undream.spec.run import RunConfig

    s = load_settings(env={})
    cfg = RunConfig(scene="s", holdout="auto")
    from undream.spec import Condition

    # what the split reads of a sequence: a scene of 24 frames
    seq = SimpleNamespace(frames=[None] * 24, condition_ranges=lambda: [(Condition("s", 24), range(24))])
    assert stages.FarmOptions.from_settings(s, cfg, seq).frames_per_task == 9
    minibatch = RunConfig(scene="s", holdout="none", attack={"name": "pgd", "frames_per_step": 4})
    assert stages.FarmOptions.from_settings(s, minibatch, seq).frames_per_task == 2
    assert stages.batches(range(18), 9) == [list(range(9)), list(range(9, 18))]
    assert [len(b) for b in stages.batches(range(24), 9)] == [8, 8, 8]  # the evaluation's 24 frames
    assert stages.batches([4, 7, 9], 10) == [[4, 7, 9]] and stages.batches([], 3) == []
    assert sum(stages.batches(range(101), 7), []) == list(range(101))
    assert max(len(b) for b in stages.batches(range(101), 7)) <= 7


def test_a_worker_process_loads_the_victims_code_before_its_first_task(monkeypatch, caplog):
    """workers.runtime.warm_up loads the bundled classifier once (the victims' model code is then
    imported) and never stops a worker from starting when it cannot."""
    import logging

    from undream import victims
    from workers import runtime

    loaded = []
    monkeypatch.setattr(victims, "load_victim", lambda spec, **kw: loaded.append((spec, kw)))
    runtime.warm_up()
    assert loaded == [("bundled:classifier", {"device": "cpu", "task": "classification", "offline": True})]

    def broken(spec, **kw):
        raise OSError("no weights here")

    monkeypatch.setattr(victims, "load_victim", broken)
    with caplog.at_level(logging.WARNING, logger="workers.runtime"):
        runtime.warm_up()  # logged, not raised
    assert any("warm-up skipped: no weights here" in r.message for r in caplog.records)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="pinning to one core needs two")
def test_a_one_core_worker_pins_every_thread_it_has(tmp_path):
    """`undream worker --threads 1` claims a core for its process: the threads that were running
    before the claim (imports start some) are pinned with it, not only the claiming thread."""
    code = ("import os, threading, sys\n"
            "from pathlib import Path\n"
            "from workers.runtime import claim_cores\n"
            "stop = threading.Event()\n"
            "early = threading.Thread(target=stop.wait); early.start()\n"
            "cores = claim_cores(1, Path(sys.argv[1]))\n"
            "late = threading.Thread(target=stop.wait); late.start()\n"
            "allowed = {t: os.sched_getaffinity(int(t)) for t in os.listdir('/proc/self/task')}\n"
            "stop.set()\n"
            "import json; print(json.dumps({'cores': cores, 'threads': len(allowed),\n"
            "                               'sets': sorted({tuple(sorted(a)) for a in allowed.values()})}))\n")
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "cores")], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout)
    assert len(got["cores"]) == 1 and got["threads"] >= 3, got
    assert got["sets"] == [got["cores"]], got  # every thread, the early one too, on the claimed core


def test_a_worker_child_has_time_to_start():
    """A child's start (Mitsuba, torch, the warm-up) took more than Celery's default 4 s on a loaded
    machine, and Celery killed and re-forked it in a loop, so no job ever ran."""
    from workers.app import PROCESS_START_TIMEOUT, create_celery_app

    app = create_celery_app(load_settings(env={}))
    assert app.conf.worker_proc_alive_timeout == PROCESS_START_TIMEOUT >= 60
