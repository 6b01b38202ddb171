"""Regularisers and print-and-capture EOT on the farm's path (issue 44): the Celery app in eager mode
steps and records as ``undream run`` does, from the run's stored config alone (the palette file is
gone by the time the tasks run)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from farm_support import make_scene, make_victim, run_config
from scheduler.local import run_local
from undream.settings import load_settings
from undream.spec.run import RunConfig
from undream.store import open_store


def test_the_farm_steps_and_records_like_a_local_run(tmp_path, mi):
    from scheduler.submit import Validator, record
    from workers.app import create_celery_app
    from workers.dispatch import CeleryDispatch

    scene, victim = make_scene(tmp_path / "scene", n_frames=2), make_victim(tmp_path / "victim")
    (tmp_path / "chart.csv").write_text("r,g,b\n0,0,0\n255,255,255\n200,30,30\n")
    extra = {"regularise": {"tv": 50.0, "nps": 0.5, "palette": str(tmp_path / "chart.csv")},
             "eot_print": {"brightness": 0.1, "gamma": 0.1, "blur": 1.0, "noise": 0.02}}
    cfg = RunConfig.from_json(run_config(scene, victim, name="phys", steps=2, holdout="none", **extra))
    local = run_local(cfg, tmp_path / "local", progress=False)

    (tmp_path / "chart.csv").unlink()  # the stored config holds the colours
    settings = load_settings(env={}, broker_url="memory://", result_backend="cache+memory://",
                             blob_url=str(tmp_path / "blobs"), cache_dir=str(tmp_path / "cache"))
    app = create_celery_app(settings)
    app.conf.task_always_eager = True
    app.conf.task_eager_propagates = True
    store = open_store(settings.database_url, settings.blob_url)
    (run_id,) = record(store, [Validator(tmp_path / "work")(cfg, Path("."))], settings, tmp_path / "out")
    CeleryDispatch(app).start(run_id)
    run = store.get_run(run_id)
    assert run.status == "done", run.error
    farm = run.results["objective_per_iteration"]
    assert set(farm) == {"loss_victim", "loss_total", "reg_tv", "reg_nps"}
    for name, values in local["objective_per_iteration"].items():
        assert farm[name] == pytest.approx(values, rel=1e-4, abs=1e-6), name
    assert np.array_equal(np.load(tmp_path / "out" / "texture_final.npy"),
                          np.load(tmp_path / "local" / "texture_final.npy"))
    store.close()
