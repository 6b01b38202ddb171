"""The control plane reads a list of runs in a fixed number of queries (issue 24, first part).

Before: ``undream status`` and the dashboard's runs list asked the store for each run's jobs and
looked for each run's final-texture blob: one query (and one file lookup) per run, 82 s for 65,000
runs. Now a run's phase and progress come from its row and one grouped count of every listed run's
jobs, so the number of SQL statements does not grow with the number of runs.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

from click.testing import CliRunner
from sqlalchemy import event
from sqlalchemy.engine import Engine

from undream.cli import main
from undream.spec.run import RunConfig
from undream.store import open_store


@contextlib.contextmanager
def _statements() -> Iterator[list[str]]:
    """Every SQL statement any engine of this process executes inside the block."""
    seen: list[str] = []

    def count(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        seen.append(statement)

    event.listen(Engine, "before_cursor_execute", count)
    try:
        yield seen
    finally:
        event.remove(Engine, "before_cursor_execute", count)


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


def _status(blobs: Path) -> tuple[str, int]:
    with _statements() as seen:
        res = CliRunner().invoke(main, ["status"], env={"UNDREAM_BLOB_URL": str(blobs)},
                                 catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res.output, len(seen)


def test_status_reads_any_number_of_runs_in_the_same_number_of_queries(tmp_path):
    few, many = tmp_path / "few", tmp_path / "many"
    _farm(few, 3)
    _farm(many, 60)
    out_few, n_few = _status(few)
    out_many, n_many = _status(many)
    assert out_many.count("\n") > out_few.count("\n") + 50  # every run is listed
    assert "0/3" in out_many  # progress of an attacking run: 0 of its 3 frame jobs done
    assert n_many == n_few, (n_few, n_many)


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
        with _statements() as seen:
            answer = client.get("/api/runs")
        assert answer.status_code == 200 and len(answer.get_json()["runs"]) == n
        counts.append(len(seen))
    assert counts[0] == counts[1], counts
