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

import json
import os
import re
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from conftest import s3_bucket, service_missing
from farm_support import ROOT, Farm, farm_inputs, fresh_postgres, redis_up, run_config, write_yaml

PLANTED = "s3cr3t-PLANTED-7f3a9"


def _planted(url: str, password: str = PLANTED) -> str:
    """``url`` (postgresql+psycopg://postgres@host/db) with the planted ``password``."""
    return re.sub(r"://([^:@/]+)@", lambda m: f"://{m[1]}:{password}@", url, count=1)


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


def test_status_of_a_run_folder_lists_its_own_runs_and_refuses_another_database(inputs, database, tmp_path):
    """Issue 41: `status --out FOLDER --database OTHER` listed OTHER's runs as the folder's, and a
    database shared by several folders' runs listed all of them. Now only the folder's runs are
    listed, and a --database that is not the folder's is one line (without its password)."""
    runs = {}
    for name in ("mine", "theirs"):
        cfg = write_yaml(tmp_path / f"{name}.yaml",
                         run_config(inputs["scene"], inputs["victim"], name=name, steps=1, store=database))
        res = _cli("run", str(cfg), "--out", str(tmp_path / name), "--no-progress")
        assert res.returncode == 0, res.stderr[-3000:]
        runs[name] = json.loads((tmp_path / name / "metadata.json").read_text())["run_id"]
    status = _cli("status", "--out", str(tmp_path / "mine"), "--database", database)
    assert status.returncode == 0, status.stderr
    assert runs["mine"][:8] in status.stdout and runs["theirs"][:8] not in status.stdout, status.stdout
    assert "1 of 1 run" in status.stdout, status.stdout
    other, drop = fresh_postgres()
    try:
        res = _cli("status", "--out", str(tmp_path / "mine"), "--database", _planted(other))
        assert res.returncode == 2 and res.stdout == "", res.stdout
        line = res.stderr.strip()
        assert "\n" not in line and "not the database of --out" in line and PLANTED not in line, line
    finally:
        drop()
    sqlite = _cli("status", "--out", str(tmp_path / "mine"), "--database", f"sqlite:///{tmp_path / 'x.db'}")
    assert sqlite.returncode == 2 and "not the database of --out" in sqlite.stderr, sqlite.stderr


def test_an_unreachable_database_is_one_line_without_its_password(tmp_path):
    url = f"postgresql://postgres:{PLANTED}@127.0.0.1:1/nowhere"
    for args in (["status", "--database", url], ["results", "x", "--database", url]):
        res = _cli(*args)
        assert res.returncode == 2, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and PLANTED not in res.stderr + res.stdout


# A password as SQLAlchemy takes it unencoded: '/' and ':' (issue 41: the redaction stopped at '/').
SLASHED = "ab/PLANTED:x/9"


def _pieces(password: str) -> list[str]:
    """``password`` and each of its runs between URL punctuation, four characters or more."""
    return [password] + [p for p in re.split(r"[/:@?#]", password) if len(p) >= 4]


def test_a_password_with_slashes_and_colons_is_kept_in_the_store(inputs, tmp_path):
    """Issue 41: ``postgresql://u:ab/cd@host/db`` (a working URL: SQLAlchemy reads the password
    ``ab/cd``) was not redacted: metadata.json, the report, the dashboard's run page and
    /api/runs/<id> showed it. A local run on such a URL, its report and every dashboard page of
    the run keep every piece of it in the store."""
    from undream.dashboard.app import create_app
    from undream.settings import load_settings

    url, drop = fresh_postgres()
    database = _planted(url, SLASHED)
    try:
        cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=1,
                                                           store=database))
        out, report = tmp_path / "out", tmp_path / "report"
        run = _cli("run", str(cfg), "--out", str(out), "--no-progress")
        assert run.returncode == 0, run.stderr[-3000:]
        rep = _cli("report", str(out), "--out", str(report), "--database", database)
        assert rep.returncode == 0, rep.stderr
        assert "postgres:***@127.0.0.1" in (out / "metadata.json").read_text()
        client = create_app(load_settings(env={"UNDREAM_DATABASE_URL": database,
                                               "UNDREAM_BLOB_URL": str(tmp_path / "blobs")})).test_client()
        run_id = json.loads((out / "metadata.json").read_text())["run_id"]
        pages = _every_page(client.application, run_id, "0")
        assert f"/api/runs/{run_id}" in pages and len(pages) >= 10, pages
        texts = {page: client.get(page, headers={"Host": "localhost"}).get_data(as_text=True) for page in pages}
        assert "postgres:***@127.0.0.1" in texts[f"/api/runs/{run_id}"]
        texts.update({str(p): p.read_text(errors="replace") for d in (out, report) for p in d.rglob("*")
                      if p.is_file() and p.suffix in (".json", ".html", ".csv", ".txt", ".log")})
        texts["stdout+stderr"] = run.stdout + run.stderr + rep.stdout + rep.stderr
        leaks = sorted((where, piece) for where, text in texts.items() for piece in _pieces(SLASHED) if piece in text)
        assert leaks == [], leaks
    finally:
        drop()


@pytest.mark.parametrize("password", ["p@ss:PLANTED-1", "PLANTED-2@x@y", ":PLANTED-3@"])
def test_a_broker_password_holding_at_signs_is_one_redacted_line(password, tmp_path):
    """Redis and kombu read a broker password up to the host's '@' (``redis://:p@ss@host``): the
    unreachable broker's error line shows none of it."""
    res = _cli("worker", "--broker", f"redis://:{password}@127.0.0.1:1/0", "--database",
               f"sqlite:///{tmp_path}/farm.db", "--blobs", str(tmp_path / "blobs"))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "redis://:***@127.0.0.1:1/0" in lines[0], res.stderr
    assert not [p for p in _pieces(password) if p in res.stderr + res.stdout], res.stderr


# `undream worker`, with Celery's loop replaced by what its log sees: Celery's logging set up at the
# worker's --loglevel (as `celery worker` does), then a blob written and read through the farm's S3
# store (as a task does). Every request signature botocore computes is recorded to grep the log for.
_WORKER = """
import sys
import botocore.auth, celery

signatures = []
_sign = botocore.auth.SigV4Auth.signature

def signature(self, string_to_sign, request):
    signatures.append(_sign(self, string_to_sign, request))
    return signatures[-1]

def worker_main(self, argv):
    from undream.store import open_farm_store
    level = next(a.split("=", 1)[1] for a in argv if a.startswith("--loglevel="))
    self.log.setup(loglevel=level, logfile=sys.argv[1], redirect_stdouts=False)
    with open_farm_store(self.undream_settings) as store:
        store.blobs.put_bytes("probe/blob", b"x")
        store.blobs.get_bytes("probe/blob")
    with open(sys.argv[2], "w") as f:
        f.write("\\n".join(signatures))

botocore.auth.SigV4Auth.signature = signature
celery.Celery.worker_main = worker_main
from undream.cli import main
main(sys.argv[3:], prog_name="undream")
"""


def test_a_debug_worker_on_s3_blobs_logs_no_key_signature_or_authorization(s3_server, tmp_path):
    """Issue 41: ``undream worker --loglevel DEBUG`` with ``s3://`` blobs wrote botocore's request
    dumps (``Authorization: AWS4-HMAC-SHA256 Credential=<key id>/…, Signature=<hex>``, the
    ``Signature:`` line of the signer) to the log. The log still holds those DEBUG lines, masked."""
    reason = redis_up()  # the worker's first check: the broker answers
    if reason:
        service_missing(reason)
    bucket = s3_bucket(s3_server, f"debug-{uuid.uuid4().hex[:8]}")
    log, signed = tmp_path / "worker.log", tmp_path / "signatures"
    env = {**os.environ, "UNDREAM_S3_ENDPOINT_URL": s3_server["endpoint"], "UNDREAM_S3_REGION": "us-east-1",
           "UNDREAM_S3_ACCESS_KEY_ID": s3_server["key_id"], "UNDREAM_S3_SECRET_ACCESS_KEY": s3_server["secret"]}
    res = subprocess.run([sys.executable, "-c", _WORKER, str(log), str(signed), "worker", "--loglevel", "DEBUG",
                          "--broker", "redis://127.0.0.1:6379/0", "--database", f"sqlite:///{tmp_path}/farm.db",
                          "--blobs", f"s3://{bucket}/blobs"], capture_output=True, text=True, cwd=ROOT, env=env,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    text = log.read_text() + res.stdout + res.stderr
    signatures = signed.read_text().split()
    assert signatures and "Sending http request" in text, text[-3000:]  # the DEBUG dumps are there
    assert "'Authorization': b'***'" in text and "Signature:\n***" in text, text[-3000:]
    secrets = [s3_server["key_id"], s3_server["secret"], *signatures]
    assert [s for s in secrets if s in text] == []


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
