"""Regularisers and print-and-capture EOT on the farm's path (issue 44): the Celery app in eager mode
steps and records as ``undream run`` does, from the run's stored config alone (the palette file is
gone by the time the tasks run)."""
from __future__ import annotations


import numpy as np
import pytest

from farm_support import eager_run, make_scene, make_victim, run_config
from scheduler.local import run_local
from undream.spec.run import RunConfig


def test_the_farm_steps_and_records_like_a_local_run(tmp_path, mi):
    scene, victim = make_scene(tmp_path / "scene", n_frames=2), make_victim(tmp_path / "victim")
    (tmp_path / "chart.csv").write_text("r,g,b\n0,0,0\n255,255,255\n200,30,30\n")
    extra = {"regularise": {"tv": 50.0, "nps": 0.5, "palette": str(tmp_path / "chart.csv")},
             "eot_print": {"brightness": 0.1, "gamma": 0.1, "blur": 1.0, "noise": 0.02}}
    cfg = RunConfig.from_json(run_config(scene, victim, name="phys", steps=2, holdout="none", **extra))
    local = run_local(cfg, tmp_path / "local", progress=False)

    (tmp_path / "chart.csv").unlink()  # the stored config holds the colours
    store, run_id = eager_run(cfg, tmp_path)
    run = store.get_run(run_id)
    assert run.status == "done", run.error
    farm = run.results["objective_per_iteration"]
    assert set(farm) == {"loss_victim", "loss_total", "reg_tv", "reg_nps"}
    for name, values in local["objective_per_iteration"].items():
        assert farm[name] == pytest.approx(values, rel=1e-4, abs=1e-6), name
    assert np.array_equal(np.load(tmp_path / "out" / "texture_final.npy"),
                          np.load(tmp_path / "local" / "texture_final.npy"))
    store.close()
