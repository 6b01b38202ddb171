"""The layering contract (``[tool.importlinter]`` in pyproject.toml, docs/architecture.md).

import-linter checks it on the real tree, every package of ``undream`` is in
a layer, and a deliberate upward import in a copy of the tree breaks it.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROOT_PACKAGES = ("undream", "scheduler", "workers")


def lint_imports(tree: Path) -> subprocess.CompletedProcess:
    """Run the venv's ``lint-imports`` on ``tree`` (packages and pyproject.toml at its top)."""
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-c",
                                             "from importlinter.cli import lint_imports_command; "
                                             "lint_imports_command()"]
    env = {**os.environ, "PYTHONPATH": str(tree)}  # this tree's packages, not the installed ones
    return subprocess.run([*cmd, "--no-cache", "--no-logo", "--config", str(tree / "pyproject.toml")],
                          cwd=tree, env=env, capture_output=True, text=True, timeout=120)


def _contracts() -> list[dict]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def test_the_tree_keeps_every_contract():
    res = lint_imports(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 broken" in res.stdout


def test_every_package_of_undream_is_in_a_layer():
    layers = next(c for c in _contracts() if c["type"] == "layers")["layers"]
    named = {m.strip().strip("()") for layer in layers for m in layer.replace(":", "|").split("|")}
    children = {f"undream.{p.stem}" for p in (ROOT / "undream").glob("*.py") if p.stem != "__init__"}
    children |= {f"undream.{p.parent.name}" for p in (ROOT / "undream").glob("*/__init__.py")}
    assert children - named == set(), "add these to the layers contract in pyproject.toml"


def _copy_tree(dst: Path) -> None:
    def only_python(folder: str, names: list[str]) -> list[str]:  # the names to leave out
        keep = lambda n: n.endswith(".py") or (Path(folder, n).is_dir() and n != "__pycache__")  # noqa: E731
        return [n for n in names if not keep(n)]
    for pkg in ROOT_PACKAGES:
        shutil.copytree(ROOT / pkg, dst / pkg, ignore=only_python)
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")


def test_an_upward_import_breaks_the_contract(tmp_path):
    _copy_tree(tmp_path)
    model = tmp_path / "undream" / "spec" / "model.py"
    model.write_text(model.read_text() + "\nimport scheduler.local  # deliberately upward\n")
    res = lint_imports(tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode != 0, out
    assert "Layers: imports point downward only BROKEN" in out
    assert "undream.spec.model -> scheduler.local" in out
