"""SIGTERM ends a command cleanly wherever it lands (undream.interrupts, undream.progress).

Before: the handler raised SystemExit wherever the main thread was. Inside a ``__del__`` Python
reports that exception and drops it, and ``undream run`` went on to its last step as if no signal
had come (a clean-clone CI waited 60 s for a run told to stop, tests/test_output_folders.py); inside
a store transaction it could interrupt the write half done.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from farm_support import ROOT, make_scene, make_victim, run_config, write_yaml

# An undream command in which the n-th call of MODULE.FUNCTION drops the first SIGTERM: the signal
# arrives while a __del__ runs, so the handler's exception is raised there and Python drops it.
DROPPED = """
import os, signal, sys
import {module} as patched
from undream.cli import main

class Sends:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        sum(range(1000))  # bytecode for the handler to run in: its exception ends here, dropped

calls = []
real = patched.{function}

def wrapper(*args, **kwargs):
    calls.append(1)
    if len(calls) == {nth}:
        Sends()  # deleted at once: the signal lands in its __del__
        print("signal sent", file=sys.stderr, flush=True)
    return real(*args, **kwargs)

patched.{function} = wrapper
sys.argv = ["undream", *sys.argv[1:]]
main()
"""


def _dropping(module: str, function: str, nth: int, *args: str) -> subprocess.CompletedProcess:
    """``undream ARGS`` whose ``nth`` call of ``module.function`` drops the first SIGTERM."""
    script = DROPPED.format(module=module, function=function, nth=nth)
    return subprocess.run([sys.executable, "-c", script, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


# A store write with a SIGTERM arriving in the middle of it: the INSERT has been sent, not committed.
DURING_WRITE = """
import os, signal, sys
from sqlalchemy import event
from undream.cli.errors import signals_end_commands
from undream.store import open_store

store = open_store(None, sys.argv[1])

@event.listens_for(store._writer, "before_cursor_execute")
def kill(conn, cursor, statement, *args):
    if statement.lstrip().upper().startswith("INSERT INTO RUNS"):
        os.kill(os.getpid(), signal.SIGTERM)
        sum(range(1000))

with signals_end_commands():
    store.create_run("interrupted", {}, 2, 0)
    print("the command went on after the write", flush=True)
"""


SPEC = {"name": "interrupted", "frames": 6,
        "camera": {"fov": 40, "resolution": [16, 16], "path": {"type": "orbit", "radius": 4, "height": 1}},
        "object": {"asset": {"name": "ball", "mesh": "builtin:sphere"},
                   "path": {"type": "static", "position": [0, 0, 0]}}}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("interrupts")
    return {"scene": make_scene(root / "scene", n_frames=2, size=16), "victim": make_victim(root / "victim")}


def test_a_sigterm_whose_exception_is_dropped_still_ends_undream_run(inputs, tmp_path):
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=40))
    out = tmp_path / "out"
    res = _dropping("scheduler.stages", "run_batch", 3, "run", str(cfg), "--out", str(out), "--no-progress")
    assert "signal sent" in res.stderr, res.stderr[-3000:]
    assert res.returncode == 128 + signal.SIGTERM, (res.returncode, res.stderr[-3000:])
    assert not (out / "results.json").exists()  # it did not run its 40 steps to the end
    from undream.store import open_store

    store = open_store(None, out / "store", create=False)
    try:
        (run,) = store.runs()
        assert run.status == "failed" and "SystemExit" in (run.error or "") and not run.owner, (run.status, run.error)
        assert run.iteration < 40
    finally:
        store.close()


def test_a_sigterm_during_a_store_write_ends_the_command_after_the_write(tmp_path):
    res = subprocess.run([sys.executable, "-c", DURING_WRITE, str(tmp_path / "store")], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 128 + signal.SIGTERM, (res.returncode, res.stdout, res.stderr[-3000:])
    assert "went on" not in res.stdout
    from undream.store import open_store

    store = open_store(None, tmp_path / "store", create=False)
    try:  # the write was whole (committed, not cut off half way), and the database takes the next one
        assert [r.name for r in store.runs()] == ["interrupted"]
        store.create_run("next", {}, 2, 0)
        assert json.dumps(sorted(r.name for r in store.runs())) == '["interrupted", "next"]'
    finally:
        store.close()


def test_a_sigterm_whose_exception_is_dropped_still_ends_undream_init(tmp_path):
    spec = write_yaml(tmp_path / "spec.yaml", SPEC)
    out = tmp_path / "scene"
    res = _dropping("undream.scenedir.init", "save_mask", 2, "init", str(spec), "--out", str(out), "--no-progress")
    assert "signal sent" in res.stderr, res.stderr[-3000:]
    assert res.returncode == 128 + signal.SIGTERM, (res.returncode, res.stderr[-3000:])
    assert not out.exists()  # stopped at the next frame and removed what it had begun
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


# An undream command whose first Dr.Jit frozen function sends SIGNAL to the process while Dr.Jit
# records it (the handler runs in the recorded Python code).
RECORDING = """
import os, signal, sys
import drjit as dr
from undream.cli import main

# The command takes SIGHUP only where it is not ignored (under nohup it is, and stays so, rightly):
# the test runs it as a shell would, with the default disposition, whatever ran the suite.
signal.signal(signal.SIGHUP, signal.SIG_DFL)

real_freeze, sent = dr.freeze, []

def freeze(fn, **options):
    def recorded(*args, **kwargs):
        if not sent:
            sent.append(1)
            print("signal sent while recording", file=sys.stderr, flush=True)
            os.kill(os.getpid(), signal.{signal})
            sum(range(1000))  # bytecode for the handler to run in, inside the recording
        return fn(*args, **kwargs)
    return real_freeze(recorded, **options)

dr.freeze = freeze
sys.argv = ["undream", *sys.argv[1:]]
main()
"""


def _recording(sig: str, *args: str) -> subprocess.CompletedProcess:
    """``undream ARGS`` with ``sig`` arriving while Dr.Jit records its first frozen function."""
    return subprocess.run([sys.executable, "-c", RECORDING.format(signal=sig), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env={**os.environ, "UNDREAM_FROZEN": "1"})


def test_a_sigterm_while_dr_jit_records_ends_undream_run_as_ctrl_c_does_and_it_resumes(inputs, tmp_path):
    """Issue 41: Dr.Jit turned the handler's exception into a RuntimeError ("error encountered while
    recording a frozen function"): 65 lines and exit 1 instead of 143, the run failed as a RuntimeError."""
    cfg = write_yaml(tmp_path / "run.yaml", run_config(inputs["scene"], inputs["victim"], steps=2))
    out = tmp_path / "out"
    res = _recording("SIGTERM", "run", str(cfg), "--out", str(out), "--no-progress")
    assert "signal sent while recording" in res.stderr, res.stderr[-3000:]
    assert res.returncode == 128 + signal.SIGTERM, (res.returncode, res.stderr[-3000:])
    assert "Traceback" not in res.stderr and "RuntimeError" not in res.stderr, res.stderr[-3000:]
    status = subprocess.run([sys.executable, "-m", "undream.cli", "status", "--out", str(out)], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert "SystemExit: 143" in status.stdout, status.stdout
    again = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(cfg), "--out", str(out), "--resume",
                            "--no-progress"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads((out / "results.json").read_text())


def test_a_sighup_while_dr_jit_records_ends_undream_init_and_leaves_nothing(tmp_path):
    spec = write_yaml(tmp_path / "spec.yaml", SPEC)
    res = _recording("SIGHUP", "init", str(spec), "--out", str(tmp_path / "scene"), "--no-progress")
    assert "signal sent while recording" in res.stderr, res.stderr[-3000:]
    assert res.returncode == 128 + signal.SIGHUP, (res.returncode, res.stderr[-3000:])
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]
