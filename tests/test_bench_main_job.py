"""benchmarks/bench_main_job.py runs ``undream run`` with the given PYTHONPATH kept after the tree's code."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_main_job", ROOT / "benchmarks" / "bench_main_job.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_dependency_on_the_given_pythonpath_is_found_by_the_run(tmp_path, monkeypatch):
    # On the lent GPU machine the dependencies were installed with pip --target and put on
    # PYTHONPATH; the benchmark replaced PYTHONPATH with the tree and every run failed
    # (No module named 'sqlalchemy').
    site = tmp_path / "site"
    site.mkdir()
    (site / "undream_bench_marker.py").write_text("WHERE = 'site'\n")
    tree = tmp_path / "tree"
    (tree / "undream_bench_tree").mkdir(parents=True)
    (tree / "undream_bench_tree" / "__init__.py").write_text("")
    monkeypatch.setenv("PYTHONPATH", str(site))
    env = _bench().run_env(tree)
    assert env["PYTHONPATH"].split(":")[0] == str(tree)
    res = subprocess.run([sys.executable, "-c", "import undream_bench_tree, undream_bench_marker; "
                          "print(undream_bench_marker.WHERE)"], cwd=tmp_path, env=env,
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "site"


def test_without_a_pythonpath_the_tree_alone(monkeypatch, tmp_path):
    monkeypatch.delenv("PYTHONPATH", raising=False)
    assert _bench().run_env(tmp_path)["PYTHONPATH"] == str(tmp_path)
