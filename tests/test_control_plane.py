"""The control plane reads a list of runs in a fixed number of queries (issue 24, first part).

Before: ``undream status`` and the dashboard's runs list asked the store for each run's jobs and
looked for each run's final-texture blob: one query (and one file lookup) per run, 82 s for 65,000
runs. Now a run's phase and progress come from its row and one grouped count of every listed run's
jobs, so the number of SQL statements does not grow with the number of runs.
"""
from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner
from sqlalchemy import event

from farm_support import sql_statements
from undream.cli import main
from undream.spec.run import RunConfig
from undream.store import open_store


def _farm(blobs: Path, n_runs: int) -> None:
    """``n_runs`` runs in every phase: queued, attacking with jobs, evaluating, done."""
    with open_store(None, blobs) as store:
        for i in range(n_runs):
            config = RunConfig.from_json({"scene": "s", "name": f"r{i}", "attack": {"name": "pgd", "steps": 2}})
            run_id = store.create_run(config.name, config.to_json(), 3, 0)
            if i % 3:
                store.queue_jobs(run_id, 0, [0, 1, 2])
            if i % 3 == 2:
                store.queue_jobs(run_id, 0, [0, 1, 2], phase="pre")


def _status(blobs: Path, *args: str) -> tuple[str, int]:
    with sql_statements() as seen:
        res = CliRunner().invoke(main, ["status", *args], env={"UNDREAM_BLOB_URL": str(blobs)},
                                 catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res.output, len(seen)


def test_status_reads_any_number_of_runs_in_the_same_number_of_queries(tmp_path):
    few, many = tmp_path / "few", tmp_path / "many"
    _farm(few, 3)
    _farm(many, 60)
    out_few, n_few = _status(few, "--all")
    out_many, n_many = _status(many, "--all")
    assert out_many.count("\n") > out_few.count("\n") + 50  # every run is listed
    assert "0/3" in out_many  # progress of an attacking run: 0 of its 3 frame jobs done
    assert n_many == n_few, (n_few, n_many)
    assert _status(many)[1] == n_few  # the default page too


def test_status_shows_the_newest_page_and_counts_every_run(tmp_path):
    _farm(tmp_path, 12)
    out, _ = _status(tmp_path, "--limit", "5")
    table, tally = out.split("\n\n")[:2]
    assert [line.split()[1] for line in table.splitlines()[1:]] == ["r11", "r10", "r9", "r8", "r7"]
    assert tally.startswith("5 of 12 runs, newest first (12 queued); more with --limit N or --all")
    out, _ = _status(tmp_path, "--state", "done")
    assert out.startswith("(none)") and "0 of 0 runs done" in out
    res = CliRunner().invoke(main, ["status", "--state", "bogus"], env={"UNDREAM_BLOB_URL": str(tmp_path)})
    assert res.exit_code == 2 and "'bogus' is not one of 'queued'" in res.output


def test_the_dashboards_runs_list_reads_any_number_of_runs_in_the_same_number_of_queries(tmp_path):
    """A guard: the runs list already counted jobs in bulk (its remaining per-run cost was a blob
    lookup for the phase, gone now); it must stay constant as the status command now is."""
    from undream.dashboard import create_app
    from undream.settings import load_settings

    counts = []
    for n in (3, 60):
        blobs = tmp_path / f"farm{n}"
        _farm(blobs, n)
        client = create_app(load_settings(env={"UNDREAM_BLOB_URL": str(blobs)})).test_client()
        client.get("/api/runs")  # the store opened and warmed once
        with sql_statements() as seen:
            answer = client.get("/api/runs")
        assert answer.status_code == 200 and len(answer.get_json()["runs"]) == min(n, 50)
        assert answer.get_json()["total"] == n
        counts.append(len(seen))
    assert counts[0] == counts[1], counts


def test_the_api_pages_through_every_run_once_newest_first(tmp_path):
    from undream.dashboard import create_app
    from undream.settings import load_settings

    _farm(tmp_path, 23)
    client = create_app(load_settings(env={"UNDREAM_BLOB_URL": str(tmp_path)})).test_client()
    names, url = [], "/api/runs?limit=10"
    while url:
        body = client.get(url).get_json()
        assert body["total"] == 23 and len(body["runs"]) <= 10
        names += [r["name"] for r in body["runs"]]
        url = body.get("next_url")
    assert names == [f"r{i}" for i in range(22, -1, -1)]
    for bad, message in (("/api/runs?limit=0", "limit '0': must be a whole number from 1 to 1000"),
                         ("/api/runs?limit=ten", "limit 'ten'"),
                         ("/api/runs?cursor=not-a-cursor", "cursor 'not-a-cursor': not a cursor of this list")):
        answer = client.get(bad)
        assert answer.status_code == 400 and message in answer.get_json()["error"], answer.get_json()
    page = client.get("/?limit=10")
    assert page.status_code == 200 and b'id="next-page"' in page.data and b"10 of 23 runs" in page.data


def test_a_page_of_runs_is_read_through_the_lists_indexes(tmp_path):
    """The page queries walk an index in order (no scan, no sort of every run): schema 4's indexes."""
    sent: list[tuple[str, tuple]] = []

    def keep(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        sent.append((statement, tuple(parameters)))

    with open_store(None, tmp_path) as store:
        event.listen(store.engine, "before_cursor_execute", keep)
        for status, sweep_id in ((None, None), ("queued", None), (None, "s")):
            sent.clear()
            store.runs_page(status, sweep_id, 10)
            sql, params = next((sql, params) for sql, params in sent if "LIMIT" in sql)
            with store.engine.connect() as conn:
                plan = " ".join(str(row[-1]) for row in conn.exec_driver_sql("EXPLAIN QUERY PLAN " + sql, params))
            assert "USING INDEX ix_runs_" in plan and "TEMP B-TREE" not in plan, plan
