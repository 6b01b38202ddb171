"""Dr.Jit's pool in a command's process: ``UNDREAM_DRJIT_THREADS`` is read, and the pool never has
fewer than two threads.

Mitsuba 3.9.1 waits forever writing or reading an EXR when Dr.Jit's pool has fewer than two threads,
and Dr.Jit's default pool is the cores the process may use. Before, ``undream run`` on one core (a
one-CPU container, ``taskset -c 0``) hung at its first texture with no word, and the farm's workers
were the only ones to read ``UNDREAM_DRJIT_THREADS``: in a command or a study script it did nothing.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from farm_support import make_scene, make_victim, run_config, write_yaml

ROOT = Path(__file__).resolve().parents[1]
TASKSET = shutil.which("taskset")
POOL = ("from undream.cli.options import local_settings; local_settings(); "
        "import drjit as dr; print(dr.thread_count())")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "UNDREAM_DRJIT_THREADS"}
    return {**env, "UNDREAM_MI_VARIANT": "llvm_ad_rgb", **extra}


def _pool(env: dict[str, str], prefix: tuple[str, ...] = ()) -> int:
    res = subprocess.run([*prefix, sys.executable, "-c", POOL], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    return int(res.stdout.split()[-1])


@pytest.mark.parametrize("value, pool", [("3", 3), ("1", 2)])
def test_the_pool_is_the_variable_and_at_least_two(value, pool):
    assert _pool(_env(UNDREAM_DRJIT_THREADS=value)) == pool


@pytest.mark.skipif(TASKSET is None, reason="needs taskset (util-linux)")
def test_one_core_gets_a_pool_of_two():
    assert _pool(_env(), (TASKSET, "-c", "0")) == 2


def test_a_bad_value_is_one_line_naming_the_variable(tmp_path):
    scene = make_scene(tmp_path / "scene", n_frames=2, size=16)
    cfg = write_yaml(tmp_path / "run.yaml", run_config(scene, make_victim(tmp_path / "victim"), steps=1))
    for bad in ("0", "two", "-1"):
        res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(cfg), "--out", str(tmp_path / "out")],
                             capture_output=True, text=True, cwd=ROOT, env=_env(UNDREAM_DRJIT_THREADS=bad),
                             timeout=120)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert f"UNDREAM_DRJIT_THREADS: must be a whole number of threads >= 1, got '{bad}'" in res.stderr
        assert not (tmp_path / "out").exists()


@pytest.mark.skipif(TASKSET is None, reason="needs taskset (util-linux)")
def test_undream_run_on_one_core_finishes(tmp_path):
    """The whole run on one core: its scene's textures written and read as EXR, two attack steps,
    the judgement. Before, it never returned (the timeout below fails the test)."""
    scene = make_scene(tmp_path / "scene", n_frames=2, size=16)
    cfg = write_yaml(tmp_path / "run.yaml", run_config(scene, make_victim(tmp_path / "victim"), steps=2))
    res = subprocess.run([TASKSET, "-c", "0", sys.executable, "-m", "undream.cli", "run", str(cfg),
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, cwd=ROOT,
                         env=_env(UNDREAM_DRJIT_THREADS="1"), timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert len(results["adversarial"]["per_frame"]) == 2  # both frames judged with the attacked texture
