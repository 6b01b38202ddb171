"""The dashboard over HTTP: the JSON API, the pages, 404 for unknown ids and path tricks,
403 for actions without the token (nothing changes), 503 with one line when the database is gone,
and ``undream dashboard`` itself serving on 127.0.0.1."""
from __future__ import annotations

import html as html_module
import http.client
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dashboard_data import build_farm  # noqa: E402

from undream.dashboard import create_app  # noqa: E402
from undream.settings import load_settings  # noqa: E402
from undream.store import RUN_STATUSES, open_store  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "dashboard-secret-0123"
MISSING = "00000000-0000-4000-8000-000000000000"


def _settings(blobs: Path, **env: str):
    return load_settings(env={"UNDREAM_BLOB_URL": str(blobs), "UNDREAM_CONNECT_TIMEOUT": "1", **env})


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    blobs = tmp_path_factory.mktemp("dash-api") / "blobs"
    with open_store(None, blobs) as store:
        ids = build_farm(store)
    app = create_app(_settings(blobs, UNDREAM_DASHBOARD_TOKEN=TOKEN,
                               UNDREAM_BROKER_URL="redis://127.0.0.1:1/0"))
    yield app.test_client(), ids, blobs
    app.extensions["undream"].close()


def _one_line(html: str) -> str:
    assert "Traceback" not in html and 'File "' not in html
    lines = re.findall(r'<p class="error-line" id="error-line">(.*?)</p>', html, re.S)
    assert len(lines) == 1 and "\n" not in lines[0].strip(), html
    return html_module.unescape(lines[0])


def test_api_runs_and_filters(farm):
    client, ids, _ = farm
    body = client.get("/api/runs").get_json()
    assert {r["status"] for r in body["runs"]} == set(RUN_STATUSES) and body["active"] == 3
    assert [r["id"] for r in client.get("/api/runs?status=cancelled").get_json()["runs"]] == [ids.runs["cancelled"]]
    assert len(client.get(f"/api/runs?sweep={ids.sweep_id}").get_json()["runs"]) == 6
    bad = client.get("/api/runs?status=bogus")
    assert bad.status_code == 400 and "not a run status" in bad.get_json()["error"]


def test_api_run_jobs_sweep_workers_health(farm):
    client, ids, _ = farm
    run = client.get(f"/api/runs/{ids.runs['done']}").get_json()
    assert run["status"] == "done" and len(run["iterations"]) == 6 and run["config"]["victim"] == "bundled:classifier"
    assert set(run["links"]["textures"]) == {"0", "1", "2", "3", "4", "5", "6", "final"}
    assert [p["n"] for p in run["attacked_metric"]] == [3] * 6 and run["attacked_metric"][-1]["value"] < 0.5
    assert run["evaluation"]["held_out"]["frames"] == 1 and run["held_out_adversarial"] == 1.0
    for url in [*run["links"]["textures"].values(), *run["links"]["charts"].values(),
                *run["links"]["frames"]["benign"].values(), *run["links"]["frames"]["adversarial"].values()]:
        res = client.get(url)
        assert res.status_code == 200 and res.mimetype == "image/png", url
    jobs = client.get(f"/api/runs/{ids.runs['running']}/jobs").get_json()
    assert jobs["columns"] == ["0", "1", "2", "3"] and jobs["rows"][1][3]["status"] == "retried"
    sweep = client.get(f"/api/sweeps/{ids.sweep_id}").get_json()
    assert sweep["name"] == "eps-sweep" and len(sweep["rows"]) == 6 and set(sweep["series"]) == {"pgd", "mifgsm"}
    assert client.get(sweep["links"]["chart"]).mimetype == "image/png"
    assert [s["id"] for s in client.get("/api/sweeps").get_json()["sweeps"]] == [ids.sweep_id]
    workers = client.get("/api/workers").get_json()
    assert {w["state"] for w in workers["workers"]} >= {"busy"}
    health = client.get("/api/health").get_json()
    assert health["status"] == "ok" and health["runs"] == 12 and health["actions_enabled"] is True


def test_pages_render(farm):
    client, ids, _ = farm
    page = client.get("/").get_data(as_text=True)
    assert page.count('class="run-link"') == 12 and 'data-refresh="5"' in page
    run = client.get(f"/runs/{ids.runs['running']}").get_data(as_text=True)
    assert 'id="job-grid"' in run and "error: RenderError: Mitsuba ran out of memory" in run
    assert 'id="cancel"' in run and 'id="resume"' not in run
    done = client.get(f"/runs/{ids.runs['done']}").get_data(as_text=True)
    assert "data-refresh" not in done and "trash_bin" in done and "umbrella" in done
    assert 'class="boxes"' not in done and 'id="boxes-key"' not in done  # a classifier's frames: no boxes
    assert "held-out frames (1): accuracy 100.0 % → <b>100.0 %</b> · attack success 0.0 %" in done
    assert "attacked frames (3): accuracy 100.0 % → <b>0.0 %</b>" in done
    assert "100.0 % → <b>100.0 %</b> <span class=\"muted\">held-out</span>" in page
    sweep = client.get(f"/sweeps/{ids.sweep_id}").get_data(as_text=True)
    assert "<th>held-out adversarial</th>" in sweep and sweep.count('class="run-link"') == 6
    assert client.get("/workers").status_code == 200
    csp = client.get("/").headers["Content-Security-Policy"]
    assert "default-src 'self'" in csp


@pytest.mark.parametrize("url", [
    f"/api/runs/{MISSING}", f"/runs/{MISSING}", f"/api/runs/{MISSING}/jobs", f"/api/sweeps/{MISSING}",
    f"/artifacts/runs/{MISSING}/texture/0.png", f"/artifacts/runs/{MISSING}/frames/benign/0.png",
    f"/artifacts/sweeps/{MISSING}/chart.png", "/api/runs/not-a-run", "/api/runs/0000",
    "/artifacts/runs/../../undream.db", "/artifacts/runs/..%2F..%2Fundream.db/texture/0.png",
    "/artifacts/runs/%2e%2e%2f%2e%2e%2fetc%2fpasswd/texture/0.png", "/artifacts/runs/%2Fetc%2Fpasswd/texture/0.png",
    "/artifacts//etc/passwd", "/artifacts/runs//etc/passwd/texture/0.png", "/artifacts/sweeps/..%2Fundream.db/chart.png",
])
def test_unknown_ids_and_path_tricks_are_404(farm, url):
    client, _, _ = farm
    res = client.get(url)
    assert res.status_code == 404, url
    assert b"SQLite format" not in res.data and b"root:" not in res.data


@pytest.mark.parametrize("tail", [
    "texture/..%2F..%2Fundream.db", "texture/%2Fetc%2Fpasswd.png", "texture/-1.png", "texture/99.png",
    "texture/1e1.png", "frames/..%2F..%2F/0.png", "frames/pre/0.png", "frames/benign/99.png",
    "frames/%2Fetc%2Fpasswd/0.png", "charts/..%2Floss.png", "charts/nope.png", "texture/final.npy",
])
def test_artifact_names_other_than_ids_and_numbers_are_404(farm, tail):
    client, ids, _ = farm
    res = client.get(f"/artifacts/runs/{ids.runs['done']}/{tail}")
    assert res.status_code == 404, tail
    assert not res.data.startswith(b"\x93NUMPY") and b"SQLite format" not in res.data


def _state(blobs: Path, run_id: str):
    with open_store(None, blobs) as store:
        run = store.get_run(run_id)
        return run.status, run.updated, run.error, run.iteration


@pytest.mark.parametrize("headers,form", [({}, {}), ({"X-Undream-Token": "wrong-token-123"}, {}),
                                          ({}, {"token": "wrong-token-123"}), ({"X-Undream-Token": ""}, {}),
                                          ({"X-Undream-Token": TOKEN[:-1]}, {})])
@pytest.mark.parametrize("action", ["cancel", "resume"])
def test_actions_without_the_right_token_are_403_and_change_nothing(farm, headers, form, action):
    client, ids, blobs = farm
    for status in ("running", "failed"):
        before = _state(blobs, ids.runs[status])
        res = client.post(f"/api/runs/{ids.runs[status]}/{action}", headers=headers, data=form)
        assert res.status_code == 403 and "token" in res.get_json()["error"]
        page = client.post(f"/runs/{ids.runs[status]}/{action}", headers=headers, data=form)
        assert page.status_code == 403 and "token" in _one_line(page.get_data(as_text=True))
        assert _state(blobs, ids.runs[status]) == before


def test_actions_are_disabled_without_a_configured_token(tmp_path):
    blobs = tmp_path / "blobs"
    with open_store(None, blobs) as store:
        ids = build_farm(store, frames=2, steps=2)
    app = create_app(_settings(blobs))
    before = _state(blobs, ids.runs["running"])
    res = app.test_client().post(f"/api/runs/{ids.runs['running']}/cancel", headers={"X-Undream-Token": TOKEN})
    assert res.status_code == 403 and "actions are disabled" in res.get_json()["error"]
    assert _state(blobs, ids.runs["running"]) == before
    assert 'id="cancel"' not in app.test_client().get(f"/runs/{ids.runs['running']}").get_data(as_text=True)
    app.extensions["undream"].close()


def test_cancel_with_the_token_and_what_does_not_apply(tmp_path):
    blobs = tmp_path / "blobs"
    with open_store(None, blobs) as store:
        ids = build_farm(store, frames=2, steps=2)
    app = create_app(_settings(blobs, UNDREAM_DASHBOARD_TOKEN=TOKEN, UNDREAM_BROKER_URL="redis://127.0.0.1:1/0"))
    client = app.test_client()
    res = client.post(f"/api/runs/{ids.runs['running']}/cancel", headers={"X-Undream-Token": TOKEN})
    assert res.status_code == 200 and res.get_json()["status"] == "cancelled"
    page = client.post(f"/runs/{ids.runs['queued']}/cancel", data={"token": TOKEN})
    assert page.status_code == 303 and page.headers["Location"].endswith(f"/runs/{ids.runs['queued']}")
    assert _state(blobs, ids.runs["queued"])[0] == "cancelled"
    again = client.post(f"/api/runs/{ids.runs['done']}/cancel", headers={"X-Undream-Token": TOKEN})
    assert again.status_code == 409 and again.get_json()["error"].endswith("is done; nothing to cancel")
    before = _state(blobs, ids.runs["failed"])
    resume = client.post(f"/api/runs/{ids.runs['failed']}/resume", headers={"X-Undream-Token": TOKEN})
    assert resume.status_code == 503 and "cannot reach the broker" in resume.get_json()["error"]
    assert _state(blobs, ids.runs["failed"]) == before
    assert client.post(f"/api/runs/{ids.runs['failed']}/delete", headers={"X-Undream-Token": TOKEN}).status_code == 404
    assert client.get(f"/api/runs/{ids.runs['running']}/cancel").status_code == 405
    app.extensions["undream"].close()


def test_an_unreachable_database_is_a_503_with_one_line(tmp_path):
    (tmp_path / "runs.db").write_text("not a database")  # a missing one is "no farm database" (test_farm_trust)
    database = f"sqlite:///{tmp_path / 'runs.db'}"
    app = create_app(_settings(tmp_path / "blobs", UNDREAM_DATABASE_URL=database))
    client = app.test_client()
    for url in ("/", f"/runs/{MISSING}", "/workers", f"/sweeps/{MISSING}"):
        res = client.get(url)
        assert res.status_code == 503, url
        line = _one_line(res.get_data(as_text=True))
        assert f"cannot open the run database at {database!r}" in line
    for url in ("/api/health", "/api/runs", f"/api/runs/{MISSING}"):
        res = client.get(url)
        assert res.status_code == 503 and "\n" not in res.get_json()["error"], url
    res = client.get(f"/artifacts/runs/{MISSING}/texture/0.png")
    assert res.status_code == 503 and "cannot open the run database" in _one_line(res.get_data(as_text=True))


@pytest.fixture
def pg_url():
    from farm_support import fresh_postgres

    url, drop = fresh_postgres()
    yield url, drop
    drop()


def test_postgresql_serves_and_a_lost_database_is_a_503(pg_url, tmp_path):
    url, drop = pg_url
    with open_store(url, tmp_path / "blobs") as store:
        ids = build_farm(store, frames=2, steps=2)
    app = create_app(_settings(tmp_path / "blobs", UNDREAM_DATABASE_URL=url))
    client = app.test_client()
    assert {r["status"] for r in client.get("/api/runs").get_json()["runs"]} == set(RUN_STATUSES)
    assert client.get(f"/runs/{ids.runs['running']}").status_code == 200
    # Issue 41: PostgreSQL refuses a NUL in a string, and ?sweep=%00 was a 503 "database error"
    for url in ("/api/runs?sweep=%00", "/api/runs?status=done%00", "/api/sweeps?limit=1%01"):
        res = client.get(url)
        assert res.status_code == 400 and "holds the control character" in res.get_json()["error"], url
    res = client.get("/?sweep=a%00b")
    assert res.status_code == 400 and "query parameter 'sweep'" in _one_line(res.get_data(as_text=True))
    assert client.get(f"/api/runs?sweep={ids.sweep_id}").status_code == 200
    drop()  # the database disappears under the running dashboard
    res = client.get("/")
    assert res.status_code == 503 and "database error" in _one_line(res.get_data(as_text=True))
    assert client.get("/api/health").status_code == 503
    app.extensions["undream"].close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _raw_get(port: int, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", path, skip_accept_encoding=True)  # the path goes out as written
    conn.endheaders()
    res = conn.getresponse()
    return res.status, res.read()


def test_the_command_serves_on_loopback_with_the_settings_options(farm):
    _, ids, blobs = farm
    port = _free_port()
    env = {**os.environ, "UNDREAM_DASHBOARD_TOKEN": TOKEN}
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "dashboard", "--port", str(port),
                             "--blobs", str(blobs), "--database", f"sqlite:///{blobs / 'undream.db'}"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        end = time.monotonic() + 60
        while True:
            try:
                status, body = _raw_get(port, "/api/health")
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < end, proc.stdout.read() if proc.stdout else ""
                time.sleep(0.2)
        assert status == 200 and json.loads(body)["runs"] == 12
        for path in ("/artifacts/runs/..%2F..%2Fundream.db/texture/0.png", "/artifacts/../undream.db",
                     f"/artifacts/runs/{ids.runs['done']}/texture/..%2F..%2F..%2Fundream.db",
                     "/artifacts/runs/%2Fetc%2Fpasswd/texture/0.png", "/static/..%2F..%2Fsettings.py",
                     "/static/../app.py"):
            status, body = _raw_get(port, path)
            assert status == 404 and b"SQLite format" not in body and b"import" not in body, path
        with socket.socket() as s:  # bound to loopback only
            assert s.connect_ex((socket.gethostbyname(socket.gethostname()), port)) != 0 or \
                socket.gethostbyname(socket.gethostname()).startswith("127.")
    finally:
        proc.terminate()
        out = proc.communicate(timeout=20)[0]
    assert f"http://127.0.0.1:{port}/" in out and "actions need the dashboard token" in out
    assert TOKEN not in out


def test_the_token_setting_is_checked_and_never_shown():
    from undream.settings import SettingsError

    settings = load_settings(env={"UNDREAM_DASHBOARD_TOKEN": TOKEN})
    assert settings.dashboard_token == TOKEN and TOKEN not in repr(settings)
    assert load_settings(env={"UNDREAM_DASHBOARD_TOKEN": ""}).dashboard_token is None
    with pytest.raises(SettingsError, match="^UNDREAM_DASHBOARD_TOKEN: must be a secret of at least 8 characters") as err:
        load_settings(env={"UNDREAM_DASHBOARD_TOKEN": "pw4x9"})
    assert "pw4x9" not in str(err.value)
