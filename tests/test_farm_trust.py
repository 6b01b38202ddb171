"""What the farm promises and must keep (issue 19, "Trust"), each through the path a user takes.

- A frame whose victim gradient holds a NaN is dropped from the iteration's
  mean, even where the renderer's backward pass turned the NaN into a finite
  texture gradient.
- A worker that cannot write its blob folder or reach its database refuses to
  start with one line; a run whose start exhausts its retries ends ``failed``
  with the reason, shown by ``undream status``.
- Read-only commands never create a farm database.
"""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from farm_support import Farm, fresh_postgres, make_scene, make_victim, redis_up, run_config, write_yaml
from undream.spec.run import RunConfig


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    base = tmp_path_factory.mktemp("trust")
    return {"root": base, "victim": make_victim(base / "victim"), "scene": make_scene(base / "scene", 3, 16)}


# --- a NaN in the victim's image gradient -------------------------------------------------------

def _nan_victim_gradient(monkeypatch, positions: set[int]) -> None:
    """The victim's image gradient on frames ``positions`` is NaN over the left half of the image
    (its loss stays finite): the renderer's backward pass still gives a finite texture gradient
    from the right half, which must not be averaged in."""
    from undream.engine import job

    real = job.victim_pass

    def nan_half(ctx, batch, images_srgb, iteration=None):
        losses, grads, records = real(ctx, batch, images_srgb, iteration)
        for i, position in enumerate(batch):
            if position in positions:
                grads[i] = grads[i].copy()
                grads[i][:, : grads[i].shape[1] // 2] = np.nan
        return losses, grads, records
    monkeypatch.setattr(job, "victim_pass", nan_half)


def _config(tiny, steps: int = 1) -> RunConfig:
    return RunConfig(scene=str(tiny["scene"]), name="nan", victim=tiny["victim"], loss="ce", holdout="none",
                     attack={"name": "mifgsm", "eps": 32.0, "steps": steps}, gradient="prb", sim_spp=2, grad_spp=2,
                     eval_spp=1, seed=5)


def test_a_frame_with_a_nan_victim_gradient_is_dropped_from_the_step(tiny, tmp_path, monkeypatch):
    from scheduler.local import run_local
    from scheduler.state import decode_state
    from undream.attacks import make_attack
    from undream.store import Store, open_store

    monkeypatch.setattr(Store, "drop_gradients", lambda *a: 0)  # this test reads iteration 0's gradients
    _nan_victim_gradient(monkeypatch, {0})
    cfg = _config(tiny)
    res = run_local(cfg, tmp_path / "out", progress=False)
    store = open_store(None, tmp_path / "out" / "store")
    run_id = res["run_id"]
    rows = {g.frame: g for g in store.frame_grads(run_id, 0)}
    assert not rows[0].finite and rows[1].finite and rows[2].finite
    assert np.isfinite(rows[0].grad).all() and np.abs(rows[0].grad).sum() > 0  # what made it slip through
    (it,) = store.iterations(run_id)
    assert (it.n_ok, it.n_bad, it.dropped_frames) == (2, 1, [0])
    assert it.loss_mean == pytest.approx((rows[1].loss + rows[2].loss) / 2)
    # The step from the finite frames only, by the attack itself:
    attack = make_attack(cfg.attack)
    T0 = torch.from_numpy(store.texture(run_id, 0))
    G = torch.from_numpy((rows[1].grad + rows[2].grad) / 2)
    expected, _ = attack.step(T0, G, it.loss_mean, decode_state(store.attack_state(run_id, 0) or {}))
    T1 = store.texture(run_id, 1)
    assert np.isfinite(T1).all()
    np.testing.assert_allclose(T1, expected.numpy(), atol=1e-6)
    assert res["frames_dropped_per_iteration"] == [1]


def test_every_frame_nan_still_fails_the_run(tiny, tmp_path, monkeypatch):
    from scheduler.iteration import AllFramesFailed
    from scheduler.local import run_local

    _nan_victim_gradient(monkeypatch, {0, 1, 2})
    with pytest.raises(AllFramesFailed, match="all 3 frames gave a non-finite gradient"):
        run_local(_config(tiny), tmp_path / "out", progress=False)


# --- a worker that cannot write its blob folder -------------------------------------------------

@pytest.fixture
def farm(tmp_path):
    from conftest import service_missing

    reason = redis_up()
    if reason:
        service_missing(reason)
    f = Farm(tmp_path, database_url=f"sqlite:///{tmp_path / 'farm.db'}", store_retries=1)
    yield f
    f.stop()


def _one_line(res: subprocess.CompletedProcess, *needles: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def test_a_worker_refuses_to_start_on_a_read_only_blob_folder(farm, read_only):
    farm.env["UNDREAM_BLOB_URL"] = str(read_only)
    t0 = time.monotonic()
    res = farm.cli("worker", timeout=60)
    _one_line(res, f"blob folder {str(read_only)!r}", "cannot write", "Read-only file system")
    assert time.monotonic() - t0 < 30
    assert not list(read_only.iterdir())


def test_a_worker_waits_for_its_unreachable_database_saying_so(farm):
    """Issue 41: a worker exited when its database did not answer at start-up (a database started
    after the workers); it now waits, as for its broker, a line at each try, its password hidden."""
    import sys

    from farm_support import ROOT, wait_for

    farm.env["UNDREAM_DATABASE_URL"] = "postgresql://alice:s3cret@127.0.0.1:1/farm"
    log = farm.root / "waiting.log"
    farm.root.mkdir(exist_ok=True)
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "worker"], cwd=ROOT, env=farm.env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: log.read_text().count("waiting for the run database") >= 2 or proc.poll() is not None,
                 60, "two waiting lines")
        assert proc.poll() is None, log.read_text()
    finally:
        proc.kill()
        proc.wait(10)
    text = log.read_text()
    assert "cannot reach the run database at 'postgresql://alice:***@127.0.0.1:1/farm'" in text, text
    assert "trying again in 1 s" in text and "trying again in 2 s" in text and "s3cret" not in text


def test_a_run_whose_start_gives_up_is_failed_with_the_reason_in_status(farm, tiny):
    run_yaml = write_yaml(farm.root / "run.yaml", run_config(tiny["scene"], tiny["victim"], name="lost"))
    run_id = farm.submit(run_yaml)
    (scene,) = (farm.blobs / "scenes").glob("*.tar")
    scene.unlink()  # what the start task needs first: it can never succeed
    farm.start_worker()
    run = farm.wait_status(run_id, ("failed",), timeout=60)
    assert run.error.startswith("start gave up after 1 retry: StoreError: blob 'scenes/"), run.error
    assert "not found in the blob folder" in run.error and "\n" not in run.error
    table = farm.cli("status")
    assert table.returncode == 0, table.stderr
    (row,) = [line for line in table.stdout.splitlines() if line.startswith(run_id[:8])]
    assert " failed " in row and "start gave up" in row
    detail = farm.cli("status", run_id[:8])
    assert f"error: {run.error}" in detail.stdout.splitlines()
    from markupsafe import escape

    from undream.dashboard import create_app

    client = create_app(farm.settings()).test_client()
    page = client.get(f"/runs/{run_id}").get_data(as_text=True)
    assert escape(run.error) in page
    assert "start gave up after 1 retry" in client.get("/").get_data(as_text=True)
    assert client.get(f"/api/runs/{run_id}").get_json()["error"] == run.error


# --- read-only commands and no farm database ----------------------------------------------------

def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


READERS = (("status",), ("status", "abcd1234"), ("results", "sweep1"), ("cancel", "abcd1234"),
           ("resume", "abcd1234"))


def test_read_only_commands_create_no_farm_database(tmp_path):
    from conftest import service_missing

    reason = redis_up()
    if reason:
        service_missing(reason)  # resume reaches the broker first
    farm = Farm(tmp_path / "farm")
    farm.root.mkdir()
    where = f"no farm database at {str(farm.blobs / 'undream.db')!r}"
    before = _tree(tmp_path)
    for args in (*READERS, ("report", "abcd1234", "--out", str(tmp_path / "report"))):
        _one_line(farm.cli(*args), where)
        assert _tree(tmp_path) == before, args
    _one_line(farm.cli("status", "--database", f"sqlite:///{tmp_path / 'other.db'}"),
              f"no farm database at 'sqlite:///{tmp_path / 'other.db'}'")
    assert _tree(tmp_path) == before


def test_the_dashboard_creates_no_farm_database(tmp_path):
    from markupsafe import escape

    from undream.dashboard import create_app
    from undream.settings import load_settings

    settings = load_settings(env={"UNDREAM_BLOB_URL": str(tmp_path / "blobs")})
    client = create_app(settings).test_client()
    res = client.get("/")
    where = escape(f"no farm database at {str(tmp_path / 'blobs' / 'undream.db')!r}")
    assert res.status_code == 503 and where in res.get_data(as_text=True)
    assert client.get("/api/runs").status_code == 503
    health = client.get("/api/health")  # healthy, no runs yet: a fresh deployment's dashboard may start first
    assert health.status_code == 200 and health.get_json()["runs"] == 0
    assert health.get_json()["note"].startswith("no farm database at ")
    assert _tree(tmp_path) == []


def test_read_only_commands_leave_an_empty_postgresql_database_empty(tmp_path):
    from sqlalchemy import create_engine, inspect

    url, drop = fresh_postgres()
    try:
        farm = Farm(tmp_path / "farm", database_url=url.replace("postgresql+psycopg://", "postgresql://"))
        for args in (("status",), ("results", "sweep1"), ("cancel", "abcd1234")):
            line = _one_line(farm.cli(*args), "no farm database at 'postgresql://", "(no undream tables")
            assert url.rsplit("/", 1)[1] in line
        engine = create_engine(url)
        assert inspect(engine).get_table_names() == []
        engine.dispose()
        assert not farm.blobs.exists()
    finally:
        drop()
