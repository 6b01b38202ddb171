"""The deployed topology as plain processes: two ``undream worker`` processes, ``undream dashboard``,
the real Redis and PostgreSQL, a blob folder they all share (the compose stack's and the manifests'
shape, without containers); a sweep runs to completion and the dashboard's JSON API reports it;
then one worker is SIGKILLed and the broker restarted in turn while a second sweep runs, which
still finishes (and the dashboard reports that too).

The broker is a Redis server of this module's own (farm_support.PrivateRedis): its restart
leaves the machine's Redis, and the farms of the other tests beside it, alone. Services missing:
skipped, or failed under UNDREAM_REQUIRE_SERVICES.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from farm_support import (
    Farm, PrivateRedis, cuda_driver_present, farm_inputs, fresh_postgres, run_config, wait_for, write_yaml,
)

ROOT = Path(__file__).resolve().parents[1]
HEALTHCHECK = ROOT / "deploy" / "docker" / "healthcheck.py"


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    """This module's own Redis server (the second test SIGKILLs it)."""
    server = PrivateRedis(tmp_path_factory.mktemp("topology-redis"))
    yield server
    server.stop()


@pytest.fixture(scope="module")
def topology(tmp_path_factory, mi, broker):
    """Two one-core workers on PostgreSQL and a Redis of their own, sharing one blob folder; the tiny
    inputs."""
    inputs = farm_inputs(tmp_path_factory, "topology", 4)
    url, drop = fresh_postgres()
    farm = Farm(inputs["root"] / "farm", database_url=url, redis=broker)
    farm.root.mkdir()
    dashboard = None
    try:
        farm.start_worker()
        farm.start_worker()
        dashboard = Dashboard(farm)
        yield farm, inputs, dashboard
    finally:
        if dashboard is not None:
            dashboard.stop()
        if not broker.up():
            broker.start()  # the workers stop cleanly against a live broker
        farm.stop()
        drop()


class Dashboard:
    """``undream dashboard`` on a free loopback port, with the farm's settings; its JSON API."""

    def __init__(self, farm: Farm) -> None:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            self.port = sock.getsockname()[1]
        self.log = farm.root / "dashboard.log"
        self.proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "dashboard", "--host", "127.0.0.1",
                                      "--port", str(self.port)], cwd=ROOT, env=farm.env,
                                     stdout=self.log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)
        self.url = f"http://127.0.0.1:{self.port}"

        def up() -> bool:
            assert self.proc.poll() is None, self.log.read_text()[-3000:]
            try:
                return self.get("/api/health")["status"] == "ok"
            except OSError:
                return False

        wait_for(up, 60, "the dashboard to answer", interval=0.2)

    def get(self, path: str) -> Any:
        with urllib.request.urlopen(self.url + path, timeout=10) as resp:
            assert resp.status == 200, path
            return json.loads(resp.read())

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)


def sweep(farm: Farm, inputs: dict, name: str, grid: dict, **cfg) -> tuple[str, list[str]]:
    """Submit a sweep over the tiny scene with ``undream sweep``; its id and its runs' ids."""
    base = run_config(inputs["scene"], inputs["victim"], name=name, **cfg)
    path = write_yaml(farm.root / f"{name}.yaml", {"name": name, "base": base, "grid": grid})
    res = farm.cli("sweep", str(path))
    assert res.returncode == 0, res.stderr
    sweep_id = res.stdout.splitlines()[0].strip()
    runs = [r.id for r in farm.store.runs(sweep_id=sweep_id)]
    assert len(runs) == len(next(iter(grid.values()))), res.stdout
    return sweep_id, runs


def healthcheck(farm: Farm, pid: int) -> subprocess.CompletedProcess:
    """deploy/docker/healthcheck.py (the images' undream-healthcheck) on the worker ``pid``."""
    return subprocess.run([sys.executable, str(HEALTHCHECK), "worker", "--pid", str(pid), "--timeout", "5"],
                          capture_output=True, text=True, cwd=ROOT, env=farm.env, timeout=60)


def results(farm: Farm, sweep_name: str) -> list[dict[str, str]]:
    """``undream results SWEEP --csv`` as rows."""
    import csv
    import io

    res = farm.cli("results", sweep_name, "--csv")
    assert res.returncode == 0, res.stderr
    return list(csv.DictReader(io.StringIO(res.stdout)))


def check_dashboard(dashboard: Dashboard, sweep_id: str, runs: list[str], steps: int) -> None:
    """The dashboard's JSON API reports the sweep and each of its runs as done, with every step."""
    health = dashboard.get("/api/health")
    assert health["status"] == "ok" and health["database"].startswith("postgresql")
    sweep = dashboard.get(f"/api/sweeps/{sweep_id}")
    assert sweep["id"] == sweep_id and sweep["statuses"] == {"done": len(runs)}
    assert sorted(r["run"] for r in sweep["rows"]) == sorted(runs)
    listed = dashboard.get(f"/api/runs?sweep={sweep_id}")
    assert sorted(r["id"] for r in listed["runs"]) == sorted(runs) and listed["active"] == 0
    for run_id in runs:
        detail = dashboard.get(f"/api/runs/{run_id}")
        assert detail["status"] == "done" and [r["k"] for r in detail["iterations"]] == list(range(steps))
        assert detail["final_texture"] and detail["evaluation"]["adversarial"] is not None


def test_a_sweep_runs_to_completion_on_two_workers(topology):
    farm, _, dashboard = topology
    assert dashboard.get("/api/health")["runs"] == 0
    for worker in farm.workers:
        res = healthcheck(farm, worker.pid)
        assert res.returncode == 0 and res.stdout.strip() == "healthy", res.stderr
    res = subprocess.run([sys.executable, str(HEALTHCHECK), "http", f"{dashboard.url}/api/health"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.strip() == "healthy", res.stderr
    sweep_id, runs = sweep(farm, topology[1], "topo", {"seed": [0, 1, 2]}, steps=3)
    for run_id in runs:
        run = farm.wait_status(run_id, timeout=120)
        assert [r.k for r in farm.store.iterations(run_id)] == [0, 1, 2]
        out = Path(run.out_dir) if run.out_dir else farm.blobs / "outputs" / f"{run.name}-{run_id[:8]}"
        assert (out / "texture_final.npy").is_file(), out  # in the shared blob folder
    assert farm.store.engine.dialect.name == "postgresql"
    rows = results(farm, "topo")
    assert sorted(r["seed"] for r in rows) == ["0", "1", "2"] and {r["status"] for r in rows} == {"done"}
    workers = {j.worker for rid in runs for j in farm.store.jobs(rid)}
    assert len(workers) >= 2, f"every job ran in one worker process: {workers}"
    check_dashboard(dashboard, sweep_id, runs, 3)
    seen = {w["worker"] for w in dashboard.get("/api/workers")["workers"]}
    assert workers <= seen, (workers, seen)
    if not cuda_driver_present():  # the GPU image's fall-back, as a worker logs it
        for log in sorted(farm.root.glob("worker*.log")):
            assert "falling back to Mitsuba variant llvm_ad_rgb: cuda_ad_rgb failed: no NVIDIA driver" \
                in log.read_text(), log


CRASH_STEPS = 40


def test_a_sweep_finishes_after_a_worker_is_killed_and_the_broker_restarted(topology):
    farm, inputs, dashboard = topology
    assert len(farm.workers) == 2 and all(w.poll() is None for w in farm.workers)
    # Long enough to be caught mid-iteration on an idle machine (with 8 transport-gradient steps the
    # runs finished in 3 s before the test saw a started job of iteration >= 1).
    sweep_id, runs = sweep(farm, inputs, "crash", {"seed": [3, 4]}, steps=CRASH_STEPS, sim_spp=32, grad_spp=32,
                           gradient="prb")

    def started_job():
        for run_id in runs:
            run = farm.store.get_run(run_id)
            jobs = [j for j in farm.store.jobs(run_id, run.iteration) if j.status == "started" and j.worker]
            if run.iteration >= 1 and jobs:
                return run_id, jobs[0]
        return None

    # 1. SIGKILL the worker (parent and child) that holds a frame job; its job runs again on the other.
    _, job = wait_for(started_job, 90, "a started frame job of iteration >= 1", interval=0.005)
    pgid = os.getpgid(int(job.worker.split(":")[1]))
    victim = next(w for w in farm.workers if w.pid == pgid)
    survivor = next(w for w in farm.workers if w.pid != pgid)
    farm.kill_worker(victim)
    assert healthcheck(farm, victim.pid).returncode == 1
    assert healthcheck(farm, survivor.pid).returncode == 0

    # The jobs the dead worker held (the one seen above, unless it finished just before the kill,
    # and the rest of its batch) go back to the queue; they must end succeeded on the survivor. The
    # redelivery itself (visibility timeout) is checked strictly in tests/test_farm_integration.py;
    # here the broker is killed next, so they may also come back through `undream resume` (once, in
    # a fresh-clone CI run, the redelivered job had not run 60 s after the kill).
    lost = [(r, j.phase, j.k, j.frame) for r in runs for j in farm.store.jobs(r)
            if j.status == "started" and j.worker == job.worker]

    # 2. SIGKILL the broker mid-sweep and start it again (empty); `undream resume` sends the runs again.
    wait_for(lambda: any(farm.store.get_run(r).status == "running" for r in runs), 60, "a run still running")
    farm.private_redis.kill()
    assert dashboard.get("/api/health")["status"] == "ok"  # the dashboard reads the store, not the broker
    farm.private_redis.start()
    for run_id in runs:
        res = farm.cli("resume", run_id)
        assert res.returncode == 0, res.stderr
        assert f"resumed {run_id}" in res.stdout or f"run {run_id} is done" in res.stdout, res.stdout
    for run_id in runs:
        farm.wait_status(run_id, timeout=120)
        assert [r.k for r in farm.store.iterations(run_id)] == list(range(CRASH_STEPS))
    jobs = {(r, j.phase, j.k, j.frame): j for r in runs for j in farm.store.jobs(r)}
    for key in lost:  # nothing the killed worker held was lost (resume counts attempts afresh)
        assert jobs[key].status == "succeeded" and jobs[key].worker != job.worker, (key, jobs[key])
    rows = results(farm, "crash")
    assert sorted(r["seed"] for r in rows) == ["3", "4"] and {r["status"] for r in rows} == {"done"}
    assert healthcheck(farm, survivor.pid).returncode == 0  # reconnected to the new broker
    check_dashboard(dashboard, sweep_id, runs, CRASH_STEPS)
