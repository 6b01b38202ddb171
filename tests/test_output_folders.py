"""The one output-folder rule (scheduler.preflight.check_output_folder), through the commands users type.

Before (issue 19, each reproduced on main): ``init --force`` deleted whatever
``--out`` held (the spec's own folder, a parent project folder, an earlier
run's output); ``run --force`` deleted the folder of a live run under it;
``run O/run.yaml --out O --force`` deleted its own config; ``submit --out``
took a scene folder, a user's folder, a file or ``/proc``; a run whose store
could not be used left ``OUT/metadata.json`` and ``OUT/store/``; SIGTERM
during ``init`` left its temporary folder behind.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from farm_support import ROOT, make_scene, make_victim, run_config, wait_for, write_yaml

SPEC = {"name": "folders", "frames": 2,
        "camera": {"fov": 40, "resolution": [16, 16], "path": {"type": "static", "position": [0, 1, 4]}},
        "object": {"asset": {"name": "ball", "mesh": "builtin:sphere"},
                   "path": {"type": "static", "position": [0, 0, 0]}}}
NOTES = {"notes.md": "a week of work\n", "data.csv": "1,2,3\n"}


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout)


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _refused(res: subprocess.CompletedProcess, *needles: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout[-2000:], res.stderr[-2000:])
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("undream: error: "), res.stderr[-3000:]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("folders")
    return {"scene": make_scene(root / "scene", n_frames=2, size=16), "victim": make_victim(root / "victim")}


def _user_folder(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    for name, text in NOTES.items():
        (path / name).write_text(text)
    return path


# -- init ---------------------------------------------------------------------------------------------


def test_init_force_keeps_a_folder_holding_the_spec_and_notes(tmp_path):
    project = _user_folder(tmp_path / "project")
    spec = write_yaml(project / "spec.yaml", SPEC)
    before = _tree(project)
    _refused(_cli("init", str(spec), "--out", str(project), "--force", "--verify-spp", "1"), "spec.yaml")
    assert _tree(project) == before


def test_init_force_keeps_a_parent_project_folder(tmp_path):
    project = _user_folder(tmp_path / "project")
    (project / "specs").mkdir()
    spec = write_yaml(project / "specs" / "spec.yaml", SPEC)
    before = _tree(project)
    _refused(_cli("init", str(spec), "--out", str(project), "--force", "--verify-spp", "1"), "input")
    assert _tree(project) == before


def test_init_force_keeps_an_earlier_runs_output_and_replaces_an_earlier_scene(tmp_path):
    spec = write_yaml(tmp_path / "spec.yaml", SPEC)
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "metadata.json").write_text(json.dumps({"undream_output": "run", "status": "done"}))
    (earlier / "results.json").write_text("{}\n")
    before = _tree(earlier)
    _refused(_cli("init", str(spec), "--out", str(earlier), "--force", "--verify-spp", "1"), "sequence.json")
    assert _tree(earlier) == before
    scene = tmp_path / "scene"
    assert _cli("init", str(spec), "--out", str(scene), "--verify-spp", "1").returncode == 0
    again = _cli("init", str(spec), "--out", str(scene), "--force", "--verify-spp", "1")
    assert again.returncode == 0, again.stderr


def test_sigterm_during_init_leaves_no_temporary_folder(tmp_path):
    spec = write_yaml(tmp_path / "spec.yaml", {**SPEC, "frames": 400})
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "init", str(spec), "--out", str(out),
                             "--verify-spp", "64", "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: list(tmp_path.glob(".out.tmp-*/verify/*.png")) or proc.poll() is not None, 120,
                 "init writing its temporary folder")
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


# -- run ----------------------------------------------------------------------------------------------


def test_run_force_keeps_the_config_it_was_given_inside_the_old_output(inputs, tmp_path):
    cfg = run_config(inputs["scene"], inputs["victim"], steps=1)
    out = tmp_path / "out"
    first = write_yaml(tmp_path / "run.yaml", cfg)
    assert _cli("run", str(first), "--out", str(out), "--no-progress").returncode == 0
    kept = write_yaml(out / "run.yaml", cfg)
    before = _tree(out)
    _refused(_cli("run", str(kept), "--out", str(out), "--force", "--no-progress"), "run.yaml", "input")
    assert _tree(out) == before


def test_run_force_never_replaces_the_folder_of_a_live_run(inputs, tmp_path):
    out = tmp_path / "out"
    slow = write_yaml(tmp_path / "slow.yaml", run_config(inputs["scene"], inputs["victim"], steps=400))
    live = subprocess.Popen([sys.executable, "-m", "undream.cli", "run", str(slow), "--out", str(out),
                             "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: (out / "store" / "undream.db").is_file() and _owned(out) or live.poll() is not None,
                 120, "the first run holding its lease")
        assert live.poll() is None, live.communicate()
        other = write_yaml(tmp_path / "other.yaml", run_config(inputs["scene"], inputs["victim"], steps=1))
        line = _refused(_cli("run", str(other), "--out", str(out), "--force", "--no-progress"), "is writing it now")
        assert str(live.pid) in line
        assert live.poll() is None  # still running, its folder intact
        assert (out / "metadata.json").is_file()
    finally:
        live.send_signal(signal.SIGTERM)
        live.wait(60)


def _owned(out: Path) -> bool:
    from undream.store import open_store

    store = open_store(None, out / "store", create=False)
    try:
        return any(r.owner for r in store.runs())
    finally:
        store.close()


@pytest.mark.parametrize("store", ["postgresql://nobody@127.0.0.1:1/nowhere", "sqlite:///{tmp}/missing/farm.db",
                                   "sqlite:///{tmp}/notadb.db"])
def test_a_run_whose_store_cannot_be_used_writes_nothing(store, inputs, tmp_path):
    (tmp_path / "notadb.db").write_text("this is not a database\n")
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=1,
                                                        store=store.format(tmp=tmp_path)))
    before = _tree(tmp_path)
    _refused(_cli("run", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"), "database")
    assert not (tmp_path / "out").exists() and _tree(tmp_path) == before


def test_a_run_name_too_long_for_the_store_is_refused_before_out_exists(inputs, tmp_path):
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], name="n" * 300, steps=1))
    _refused(_cli("run", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"), "name")
    assert not (tmp_path / "out").exists()


# -- submit and sweep: --out checked when submitted ---------------------------------------------------


@pytest.mark.parametrize("kind", ["scene", "user folder", "file", "proc"])
def test_submit_checks_out_at_submit_time(kind, inputs, tmp_path):
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=1))
    out = {"scene": inputs["scene"], "user folder": _user_folder(tmp_path / "mine"),
           "file": tmp_path / "run.yaml", "proc": Path("/proc/undream-out")}[kind]
    before = _tree(Path(out)) if Path(out).is_dir() and kind != "proc" else None
    for command, target in (("submit", cfg), ("sweep", _sweep(tmp_path))):
        _refused(_cli(command, str(target), "--out", str(out), "--broker", "redis://127.0.0.1:1/0",
                      "--blobs", str(tmp_path / "blobs")), str(out))
    if before is not None:
        assert _tree(Path(out)) == before
    assert not (tmp_path / "blobs").exists()


def _sweep(tmp_path: Path) -> Path:
    return write_yaml(tmp_path / "sweep.yaml", {"name": "s", "run": "run.yaml", "grid": {"seed": [0]}})


def test_a_worker_never_writes_outputs_into_a_folder_that_is_not_its_runs(tmp_path):
    from scheduler.outputs import _check_own
    from undream.errors import StoreError

    _check_own(tmp_path / "absent", "r1")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "metadata.json").write_text(json.dumps({"run_id": "r1", "undream_output": "run"}))
    _check_own(mine, "r1")
    for folder in (_user_folder(tmp_path / "user"), mine):
        with pytest.raises(StoreError, match="not this run's outputs"):
            _check_own(folder, "r2")
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "sequence.json").write_text("{}")
    (scene / "metadata.json").write_text(json.dumps({"undream_output": "run"}))
    with pytest.raises(StoreError, match="a scene"):
        _check_own(scene, "r1")


def test_victims_commands_never_write_into_a_users_folder(tmp_path):
    """make-dataset wrote its images over a folder's own files; train wrote config.json, the weights and
    README.md (the model card) over whatever --out held. Both now need a new or empty folder, checked
    before any rendering or training (so the data sets need not even exist for the refusal)."""
    user = _user_folder(tmp_path / "thesis")
    (user / "images").mkdir()
    (user / "images" / "000000.png").write_bytes(b"my figure")
    before = _tree(user)
    _refused(_cli("victims", "make-dataset", "--out", str(user), "--n", "2"), "already holds files")
    _refused(_cli("victims", "train", "--task", "classification", "--data", str(tmp_path / "data"),
                  "--test", str(tmp_path / "test"), "--out", str(user)), "already holds files")
    _refused(_cli("victims", "train", "--task", "classification", "--data", str(user / "images"),
                  "--test", str(tmp_path / "test"), "--out", str(user)), "holds this command's input")
    assert _tree(user) == before


def test_victims_train_never_writes_its_model_inside_its_own_test_set(tmp_path):
    """Issue 41: `victims train --out TEST/model` was accepted (the check looked for inputs inside
    --out, not for --out inside an input): the model landed in the held-out data set. Refused in one
    line before any training, naming the folder; nothing written."""
    test = tmp_path / "test"
    (test / "images").mkdir(parents=True)
    (tmp_path / "data").mkdir()
    before = _tree(test)
    for out in (test / "model", test / "images" / "model"):
        line = _refused(_cli("victims", "train", "--task", "classification", "--data", str(tmp_path / "data"),
                             "--test", str(test), "--out", str(out)), f"--out {out}", "lies inside this command's input")
        assert str(test) in line
    assert _tree(test) == before and sorted(p.name for p in test.iterdir()) == ["images"]


def test_sigterm_during_make_dataset_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "ds"
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "victims", "make-dataset", "--out", str(out),
                             "--n", "5000", "--spp", "1", "--no-progress"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: proc.poll() is not None or ((out / "images").is_dir() and any((out / "images").iterdir())),
                 120, "the first image")
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode != 0
    assert not out.exists(), sorted(p.name for p in out.rglob("*"))[:10]
