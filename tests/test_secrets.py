"""No secret leaves the store: a password planted in the database URL appears in no artifact.

Before (issue 19, reproduced on main): ``store: postgresql://user:PASSWORD@…``
put the password in ``OUT/metadata.json``, in the report's ``index.html`` and
in the dashboard's run page and ``/api/runs/<id>`` (no token needed), and the
dashboard answered any ``Host`` header (DNS rebinding could read it).

The password is planted in PostgreSQL URLs (the test server trusts every
connection, so any password connects). A local run, its report, ``status``,
a farm run through a real Redis and a real worker process, every dashboard
page and API answer, and the error line of an unreachable database are all
grepped for it: zero hits, while the run itself worked.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from farm_support import ROOT, Farm, farm_inputs, fresh_postgres, run_config, write_yaml

PLANTED = "s3cr3t-PLANTED-7f3a9"


def _planted(url: str) -> str:
    """``url`` (postgresql+psycopg://postgres@host/db) with the planted password."""
    return re.sub(r"://([^:@/]+)@", rf"://\1:{PLANTED}@", url, count=1)


def _hits(folder: Path) -> list[str]:
    """Files under ``folder`` whose bytes hold the planted password."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")
                  if p.is_file() and PLANTED.encode() in p.read_bytes())


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          env=env, timeout=300)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return farm_inputs(tmp_path_factory, "secrets", n_frames=2)


@pytest.fixture(scope="module")
def database():
    url, drop = fresh_postgres()
    yield _planted(url)
    drop()


def test_the_planted_password_really_connects(database):
    """The test can fail: the planted URL is a working one, so a leak would be a real one."""
    from sqlalchemy import create_engine, text

    assert PLANTED in database

    engine = create_engine(database.replace("postgresql://", "postgresql+psycopg://", 1)
                           if database.startswith("postgresql://") else database)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT 1")).scalar() == 1
    engine.dispose()


def test_a_local_run_its_report_and_status_keep_the_password_in_the_store(inputs, database, tmp_path):
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=1, store=database))
    out, report = tmp_path / "out", tmp_path / "report"
    run = _cli("run", str(cfg), "--out", str(out), "--no-progress")
    assert run.returncode == 0, run.stderr[-3000:]
    assert (out / "results.json").is_file()
    status = _cli("status", "--out", str(out), "--database", database)
    assert status.returncode == 0, status.stderr
    rep = _cli("report", str(out), "--out", str(report), "--database", database)
    assert rep.returncode == 0, rep.stderr
    assert "***" in (out / "metadata.json").read_text()  # the URL is there, redacted
    assert _hits(out) == [] and _hits(report) == []
    for res in (run, status, rep):
        assert PLANTED not in res.stdout + res.stderr


def test_status_of_a_run_folder_asks_for_the_password_it_does_not_keep(inputs, database, tmp_path):
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=1, store=database))
    out = tmp_path / "out"
    assert _cli("run", str(cfg), "--out", str(out), "--no-progress").returncode == 0
    res = _cli("status", "--out", str(out))
    assert res.returncode == 2 and "--database" in res.stderr and PLANTED not in res.stderr


def test_an_unreachable_database_is_one_line_without_its_password(tmp_path):
    url = f"postgresql://postgres:{PLANTED}@127.0.0.1:1/nowhere"
    for args in (["status", "--database", url], ["results", "x", "--database", url]):
        res = _cli(*args)
        assert res.returncode == 2, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and PLANTED not in res.stderr + res.stdout


def test_a_farm_run_and_every_dashboard_page_keep_the_password_in_the_store(inputs, database, tmp_path):
    from undream.dashboard.app import create_app
    from undream.settings import load_settings

    farm = Farm(tmp_path / "farm", database_url=database)
    try:
        cfg = write_yaml(tmp_path / "farm.yaml", run_config(inputs["scene"], inputs["victim"], steps=1))
        out = tmp_path / "farm-out"
        submitted = farm.cli("submit", str(cfg), "--out", str(out))
        assert submitted.returncode == 0, submitted.stderr
        run_id = submitted.stdout.strip().splitlines()[-1]
        farm.start_worker()
        farm.wait_status(run_id, timeout=180)
        status = farm.cli("status")
        sweep = write_yaml(tmp_path / "sweep.yaml", {"name": "planted", "run": "farm.yaml",
                                                     "grid": {"attack.eps": [4]}})
        swept = farm.cli("sweep", str(sweep), "--out", str(tmp_path / "sweep-out"))
        assert swept.returncode == 0, swept.stderr
        sweep_id = swept.stdout.splitlines()[0].strip()
        farm.stop()
        logs = "".join(p.read_text() for p in farm.root.glob("worker*.log"))
        assert PLANTED not in logs + status.stdout + status.stderr + submitted.stdout + swept.stdout
        assert _hits(out) == [] and _hits(farm.blobs) == []

        settings = load_settings(env=farm.env)
        client = create_app(settings).test_client()
        local = [r for r in farm.store.runs() if r.config.get("store")]  # the local runs above, same database
        assert local and PLANTED in local[0].config["store"]  # the store keeps it: the pages must not show it
        pages = sorted({p for r in [run_id, *(r.id for r in local)] for p in _every_page(client.application, r,
                                                                                         sweep_id)})
        assert len(pages) >= 10, pages
        for page in pages:
            res = client.get(page, headers={"Host": "127.0.0.1:8150"})
            assert res.status_code < 500, (page, res.status_code)
            assert PLANTED.encode() not in res.data, page
        detail = client.get(f"/api/runs/{local[0].id}", headers={"Host": "localhost:8150"}).get_json()
        assert "***@" in detail["config"]["store"]
    finally:
        farm.stop()


def _every_page(app, run_id: str, sweep_id: str) -> list[str]:
    """A URL of every GET route of the dashboard, with this run's and sweep's ids filled in."""
    pages = []
    for rule in app.url_map.iter_rules():
        if "GET" not in rule.methods or rule.endpoint == "static":
            continue
        values = {}
        for arg in rule.arguments:
            values[arg] = {"run_id": run_id, "sweep_id": sweep_id}.get(arg, "0")
        try:
            pages.append(app.url_map.bind("localhost").build(rule.endpoint, values))
        except Exception:  # a route with arguments this farm has no value for
            continue
    return sorted(set(pages))


@pytest.mark.parametrize("host, served", [
    ("127.0.0.1:8150", True), ("localhost:8150", True), ("[::1]:8150", True), ("10.1.2.3:8150", True),
    ("farm.example:8150", True), ("evil.example", False), ("127.0.0.1.nip.example:8150", False),
])
def test_the_dashboard_refuses_host_names_it_does_not_serve(host, served, tmp_path):
    from undream.dashboard.app import create_app
    from undream.settings import load_settings

    settings = load_settings(env={"UNDREAM_BLOB_URL": str(tmp_path / "blobs")})
    client = create_app(settings, allowed_hosts=("farm.example",)).test_client()
    res = client.get("/api/health", headers={"Host": host})
    assert (res.status_code != 421) == served, (host, res.status_code, res.data)
