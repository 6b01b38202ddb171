"""The farm's commands on bad input and unreachable services: one stderr line, exit 2, nothing queued.

Also ``undream sweep`` and ``undream results`` end to end on the eager
stages (the runs are driven in this process; the CLI only records them).
"""
from __future__ import annotations

import csv
import io

import pytest

from farm_support import Farm, farm_inputs, redis_client, run_config, write_yaml

SECRET = "s3cret"
DEAD_BROKER = f"redis://:{SECRET}@127.0.0.1:1/0"
DEAD_DATABASE = f"postgresql://alice:{SECRET}@127.0.0.1:1/farm"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    return farm_inputs(tmp_path_factory, "farm_cli", 2)


@pytest.fixture
def farm(tiny, tmp_path):
    f = Farm(tmp_path)
    yield f
    f.stop()


def _one_line(res, *needles: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert SECRET not in res.stderr + res.stdout
    return lines[0]


def _nothing_queued(farm: Farm) -> None:
    r = redis_client(farm.db)
    assert r.dbsize() == 0, r.keys()
    if (farm.blobs / "undream.db").exists():
        assert farm.store.runs() == []
    assert not (farm.blobs / "scenes").exists() and not (farm.blobs / "runs").exists()


def test_an_unreachable_broker_is_one_line_naming_it(farm, tiny):
    run_yaml = write_yaml(farm.root / "run.yaml", run_config(tiny["scene"], tiny["victim"]))
    farm.env["UNDREAM_BROKER_URL"] = DEAD_BROKER
    for args in (("submit", str(run_yaml)), ("resume", "abcd1234"), ("worker",)):
        _one_line(farm.cli(*args), "cannot reach the broker at 'redis://:***@127.0.0.1:1/0'")
    assert not farm.blobs.exists()  # nothing written before the broker answered


def test_an_unreachable_database_is_one_line_naming_it(farm, tiny):
    run_yaml = write_yaml(farm.root / "run.yaml", run_config(tiny["scene"], tiny["victim"]))
    farm.env["UNDREAM_DATABASE_URL"] = DEAD_DATABASE
    for args in (("status",), ("cancel", "abcd1234"), ("submit", str(run_yaml))):
        _one_line(farm.cli(*args), "cannot open the run database at 'postgresql://alice:***@127.0.0.1:1/farm'")
    _nothing_queued(farm)


def test_an_unknown_run_is_one_line(farm):
    farm.store.close()  # a farm database with no runs (without one: "no farm database", test_farm_trust)
    for args in (("status", "nope"), ("cancel", "nope"), ("resume", "nope")):
        _one_line(farm.cli(*args), "run 'nope': not found")
    _one_line(farm.cli("results", "nosuchsweep"), "sweep 'nosuchsweep': not found")


@pytest.mark.parametrize("change, needles", [
    ({"label": "giraffe"}, ["bad.yaml: label", "giraffe", "classes"]),
    ({"attack": {"name": "fgsm-9000"}}, ["bad.yaml: attack.name", "fgsm-9000"]),
    ({"victim": "/nowhere/victim"}, ["bad.yaml", "/nowhere/victim"]),
])
def test_a_bad_run_is_rejected_before_anything_is_queued(farm, tiny, change, needles):
    cfg = {**run_config(tiny["scene"], tiny["victim"]), **change}
    if "attack" in change:
        cfg["attack"] = {"name": "pgd", "eps": 8, "steps": 2, **change["attack"]}
    res = farm.cli("submit", str(write_yaml(farm.root / "bad.yaml", cfg)))
    _one_line(res, *needles)
    _nothing_queued(farm)


def test_a_bad_settings_file_is_one_line(farm, tmp_path):
    path = write_yaml(tmp_path / "farm.yaml", {"concurrency": "lots"})
    _one_line(farm.cli("status", "--settings", str(path)), "farm.yaml: concurrency: must be an integer")


def test_a_sweep_is_validated_whole_then_recorded_and_its_results_tabled(farm, tiny):
    """A bad combination rejects the whole sweep; a good one records a run per combination."""
    from scheduler import stages
    from scheduler.local import LocalDispatch, drain
    from scheduler.contexts import ContextCache

    write_yaml(farm.root / "run.yaml", run_config(tiny["scene"], tiny["victim"], steps=1))
    bad = write_yaml(farm.root / "bad.yaml", {"name": "g", "run": "run.yaml",
                                              "grid": {"label": ["sphere", "giraffe"]}})
    _one_line(farm.cli("sweep", str(bad)), "bad.yaml: run 1 (g-001)", "giraffe")
    _nothing_queued(farm)
    good = write_yaml(farm.root / "sweep.yaml", {"name": "eps", "run": "run.yaml",
                                                 "grid": {"attack.eps": [8, 16], "seed": [0, 1]}})
    res = farm.cli("sweep", str(good), "--out", str(farm.root / "out"))
    assert res.returncode == 0, res.stderr
    sweep_id = res.stdout.splitlines()[0]
    runs = farm.store.runs(sweep_id=sweep_id)
    assert [r.name for r in runs] == [f"eps-{i:03d}" for i in range(4)]
    assert len({r.scene_ref for r in runs}) == 1  # one scene blob for the whole sweep
    assert redis_client(farm.db).llen("undream.control") == 4  # one start per run, nothing run yet
    contexts = ContextCache(farm.store, farm.root / "cache")
    dispatch = LocalDispatch()
    for run in runs[:3]:  # the fourth stays queued
        dispatch.start(run.id)
    drain(farm.store, contexts, dispatch)
    assert contexts.built == {"contexts": 3, "scenes": 1, "victims": 1}  # one scene and victim shared
    assert [r.status for r in farm.store.runs(sweep_id=sweep_id)] == ["done"] * 3 + ["queued"]
    assert (farm.root / "out" / "eps-000" / "results.json").is_file()
    table = farm.cli("results", "eps")
    assert table.returncode == 0, table.stderr
    assert table.stdout.splitlines()[0].split()[:5] == ["run", "name", "attack.eps", "seed", "status"]
    rows = list(csv.DictReader(io.StringIO(farm.cli("results", sweep_id[:8], "--csv").stdout)))
    assert [(r["attack.eps"], r["seed"], r["status"]) for r in rows] == \
        [("8", "0", "done"), ("8", "1", "done"), ("16", "0", "done"), ("16", "1", "queued")]
    assert rows[0]["metric"] == "accuracy" and rows[3]["benign"] == ""
    assert stages.cancel(farm.store, runs[3].id)


def test_an_interrupted_sweep_records_nothing_and_a_half_sent_one_is_resumed(farm, tiny, monkeypatch):
    """Ctrl-C while the runs are recorded leaves no sweep and no run; a broker lost after one start
    leaves every run queued, and `undream resume SWEEP` sends them all: each run starts once."""
    from collections import Counter

    from click.testing import CliRunner
    from sqlalchemy import Engine, event

    from scheduler import stages
    from scheduler.contexts import ContextCache
    from scheduler.local import LocalDispatch
    from undream.cli import farm as farm_cli
    from undream.cli import main

    class Flaky(LocalDispatch):
        """Starts queued here (a broker lost after ``sent`` of them); each run's planned chords counted."""

        def __init__(self, sent: int | None) -> None:
            super().__init__()
            self.sent, self.planned = sent, Counter()

        def start(self, run_id: str) -> None:
            if self.sent is not None and len(self.queue) >= self.sent:
                raise ConnectionError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")
            super().start(run_id)

        def frames(self, run_id: str, phase: str, k: int, batches: list[list[int]]) -> None:
            self.planned[run_id, phase, k] += 1

    def cli(*args: str):
        return CliRunner().invoke(main, list(args), env=farm.env)

    def interrupt(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        if statement.lstrip().upper().startswith("INSERT INTO RUNS"):
            raise KeyboardInterrupt

    write_yaml(farm.root / "run.yaml", run_config(tiny["scene"], tiny["victim"], steps=1))
    sweep_yaml = write_yaml(farm.root / "sweep.yaml", {"name": "seeds", "run": "run.yaml",
                                                       "grid": {"seed": [0, 1, 2]}})
    event.listen(Engine, "before_cursor_execute", interrupt)
    try:
        res = cli("sweep", str(sweep_yaml))
    finally:
        event.remove(Engine, "before_cursor_execute", interrupt)
    assert res.exit_code == 1 and "aborted" in res.stderr, (res.exit_code, res.output)
    assert farm.store.runs() == [] and redis_client(farm.db).dbsize() == 0
    _one_line(farm.cli("results", "seeds"), "sweep 'seeds': not found")  # no sweep row either

    dispatch = Flaky(sent=1)
    monkeypatch.setattr(farm_cli, "_dispatch", lambda app: dispatch)
    res = cli("sweep", str(sweep_yaml))
    sweep_id = res.stdout.splitlines()[0]
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
    assert f"sweep {sweep_id} recorded but not sent to the broker (Error 111" in res.stderr
    assert f"send it with `undream resume {sweep_id}`" in res.stderr
    runs = farm.store.runs(sweep_id=sweep_id)
    assert [r.status for r in runs] == ["queued"] * 3 and list(dispatch.queue) == [("start", runs[0].id)]

    dispatch.sent = None
    res = cli("resume", sweep_id[:8])
    assert res.exit_code == 0, res.output
    assert res.stdout.strip() == f"resumed sweep {sweep_id}: 3 queued run(s) sent"
    assert [item[1] for item in dispatch.queue] == [runs[0].id] + [r.id for r in runs]  # run 0's start twice
    contexts = ContextCache(farm.store, farm.root / "cache")
    outcomes = [stages.start(farm.store, contexts, item[1], dispatch) for item in dispatch.queue]
    assert outcomes == ["started"] * 4
    # run 0's second start plans iteration 0 again (duplicate work, one step: see stages.start)
    assert dispatch.planned == Counter({(runs[0].id, "attack", 0): 2, **{(r.id, "attack", 0): 1 for r in runs[1:]}})
    assert [r.status for r in farm.store.runs(sweep_id=sweep_id)] == ["running"] * 3
    assert cli("resume", "seeds").stdout.strip() == f"resumed sweep {sweep_id}: 0 queued run(s) sent, 3 running run(s) resumed"
