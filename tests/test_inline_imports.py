"""Imports sit at the top of their module, except at the heavy-import boundary (issue 20).

A function-level import hides the dependency graph, so one is allowed only where importing at the
top would load something slow or forbidden in some process: a package of :data:`HEAVY`, one of
undream's own modules that loads such a package when imported (:data:`HEAVY_OWN`, checked below
to really do so), and three places named with their reason (:data:`CLI_START`, :data:`SPEC_LIGHT`,
:data:`CYCLES`). An optional dependency tried under ``except ImportError`` is allowed too.
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("undream", "scheduler", "workers")

# Top-level packages: slow to import, or never to be imported in some process (the worker's parent
# loads no renderer: tests/test_farm_logic.py::test_the_worker_parent_imports_no_renderer).
HEAVY = {
    "mitsuba", "drjit",            # the renderer: only in the processes that render
    "torch", "transformers",       # victims and attacks: seconds to import
    "bpy", "mathutils",            # exist only in Blender's own Python
    "matplotlib", "scipy",         # hundreds of ms (scipy.spatial.transform ~0.4 s)
    "pycocotools",                 # AP only
    "celery", "sqlalchemy",        # the farm and the store
    "alembic",                     # ~80 ms; only when a database is made or upgraded
    "flask", "waitress",           # the dashboard
    "boto3", "botocore",           # S3 blobs only (undream.store.blob_s3): hundreds of ms
}

# undream's own modules that load a HEAVY package when imported (or, for undream.attacks, when one
# of its lazily-loaded names is imported). test_heavy_own_is_heavy checks each use really does.
HEAVY_OWN = {
    "undream.store": "SQLAlchemy",
    "scheduler.benign": "undream.store (SQLAlchemy)",
    "scheduler.lease": "undream.store (SQLAlchemy)",
    "scheduler.local": "undream.store (SQLAlchemy)",
    "scheduler.scenes": "undream.store (SQLAlchemy)",
    "scheduler.stages": "undream.store (SQLAlchemy)",
    "scheduler.submit": "undream.store (SQLAlchemy)",
    "workers.app": "undream.store (SQLAlchemy); Celery",
    "workers.main": "workers.app",
    "undream.victims": "torch",
    "undream.attacks": "torch (the package's names load their torch module when imported)",
    "undream.engine.context": "torch (victims, attacks)",
    "undream.engine.job": "undream.engine.context (torch)",
    "undream.engine.algorithm": "torch (victims, attacks)",
    "undream.engine.patch": "torch",
    "undream.training": "torch, scipy",
    "undream.render.jitter": "scipy.spatial.transform",
    "undream.render.transport": "scipy.sparse",
    "undream.scene.trajectory": "scipy",
    "undream.sim.blender_scene": "bpy (Blender's Python only)",
    "undream.dashboard.app": "Flask",
}

# `undream --help` and one-line errors stay fast: `import undream.cli` loads only these of undream
# (checked by test_the_cli_starts_light); a command imports the rest of undream, scheduler and
# workers when it runs.
CLI_START = ("undream.cli", "undream.errors", "undream.interrupts", "undream.redact", "undream.runlist")

# `import undream.spec` stays ~20 ms (docs/architecture.md): numpy (~120 ms) and yaml (~15 ms) load
# only when a JSON file's depth is measured or a YAML file is read.
SPEC_LIGHT = {"undream/spec/io.py": ("numpy", "yaml", "undream.spec.yaml_strict")}

# A package that imports its own modules, which import the package back (at its top: a cycle).
CYCLES = {"undream/sim/__init__.py": ("undream.sim", "the backends import register_backend from undream.sim")}


def _within(module: str, names) -> bool:
    return any(module == n or module.startswith(n + ".") for n in names)


def _targets(node: ast.Import | ast.ImportFrom, rel: Path) -> list[str]:
    """The modules an import statement names: ``from m import a`` names m and, if a package's
    module, m.a."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    module = node.module or ""
    if node.level:
        base = list(rel.with_suffix("").parts)[:-node.level]
        module = ".".join(base + ([module] if module else []))
    return [module] + [f"{module}.{a.name}" for a in node.names]


def _guarded(parents: list[ast.AST]) -> bool:
    """Inside ``try: ... except ImportError`` (an optional dependency)."""
    for p in parents:
        if isinstance(p, ast.Try):
            for h in p.handlers:
                names = [h.type] if not isinstance(h.type, ast.Tuple) else h.type.elts
                if any(isinstance(n, ast.Name) and n.id in ("ImportError", "ModuleNotFoundError") for n in names):
                    return True
    return False


def _inline_imports():
    """(relative path, line, statement, target modules) of every import inside a function."""
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT)
            found = []

            def walk(node, parents, in_function):
                for child in ast.iter_child_nodes(node):
                    if in_function and isinstance(child, (ast.Import, ast.ImportFrom)) and not _guarded(parents):
                        found.append((rel.as_posix(), child.lineno, ast.unparse(child), _targets(child, rel)))
                    walk(child, parents + [child],
                         in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

            walk(ast.parse(path.read_text(), str(path)), [], False)
            yield from found


def _why_allowed(rel: str, targets: list[str]) -> str | None:
    if any(t.split(".")[0] in HEAVY for t in targets):
        return "HEAVY"
    if any(_within(t, HEAVY_OWN) for t in targets):
        return "HEAVY_OWN"
    if rel.startswith("undream/cli/") and any(t.split(".")[0] in PACKAGES for t in targets) \
            and not _within(targets[0], CLI_START):
        return "CLI_START"
    if any(_within(t, SPEC_LIGHT.get(rel, ())) for t in targets):
        return "SPEC_LIGHT"
    if rel in CYCLES and _within(targets[0], (CYCLES[rel][0],)):
        return "CYCLES"
    return None


def test_function_level_imports_are_heavy_only():
    bad = [f"{rel}:{line}: {stmt}" for rel, line, stmt, targets in _inline_imports()
           if _why_allowed(rel, targets) is None]
    assert not bad, ("imports inside functions of modules that are not heavy (move them to the module's "
                     "top, or add the module to HEAVY/HEAVY_OWN with its reason):\n" + "\n".join(bad))


_PROBE = """
import sys
class Hit(BaseException):
    pass
class Finder:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            raise Hit(name)
sys.meta_path.insert(0, Finder())
light = []
for stmt in STATEMENTS:
    try:
        exec(stmt)
    except Hit:
        continue
    light.append(stmt)
print(light)
"""


def test_heavy_own_is_heavy():
    """Each import allowed by HEAVY_OWN loads a HEAVY package (stopped at the first one), and each
    entry is used."""
    uses = {}
    for rel, line, stmt, targets in _inline_imports():
        if _why_allowed(rel, targets) == "HEAVY_OWN":
            for key in HEAVY_OWN:
                if any(_within(t, (key,)) for t in targets):
                    uses.setdefault(key, set()).add(stmt)
    assert sorted(uses) == sorted(HEAVY_OWN), f"unused HEAVY_OWN entries: {sorted(set(HEAVY_OWN) - set(uses))}"
    statements = sorted(set().union(*uses.values()))
    code = f"HEAVY = {sorted(HEAVY)!r}\nSTATEMENTS = {statements!r}\n" + _PROBE
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", f"these load nothing heavy, so belong at the module top: {out.stdout}"


def test_the_cli_starts_light():
    code = ("import sys, undream.cli\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('undream', 'scheduler', 'workers')))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = eval(out.stdout)
    assert [m for m in loaded if m != "undream" and not _within(m, CLI_START)] == []


_REFUSED = """
import sys
from undream.cli import main
try:
    main(sys.argv[1:], prog_name="undream")
except SystemExit as exit:
    print(exit.code, sorted(m for m in ("torch", "transformers") if m in sys.modules))
"""


@pytest.mark.parametrize("command, says", [
    (["run", "{bad}", "--out", "{tmp}/out"], "bogus: unknown field"),
    (["submit", "{bad}", "--broker", "redis://127.0.0.1:1/0"], "bogus: unknown field"),
    (["sweep", "{sweep}", "--broker", "redis://127.0.0.1:1/0"], "bogus: unknown field"),
    (["run", "{good}", "--out", "{tmp}/theirs", "--force"], "--force only replaces a folder that `undream run` wrote"),
    (["run", "{unknown}", "--out", "{tmp}/out"], "conditions.holdout: 'weather_fog' is not a condition")],
    ids=["run-malformed", "submit-malformed", "sweep-malformed", "run-force-on-a-foreign-folder",
         "run-holdout-not-a-condition"])
def test_a_refused_command_loads_no_torch(tmp_path, command, says):
    """A config refused for its fields, an --out that `undream run` may not replace, or conditions
    that do not fit the scene, is one line before torch and the victims' libraries load: 0.2 s here
    for a malformed config, 1.4–1.7 s for the folder or the conditions, where each took 2–3 s
    (Mitsuba's variant is still chosen at the edge: ``undream.cli.options.local_settings``)."""
    good = {"name": "quick", "scene": str(ROOT / "examples" / "bin_orbit.yaml"), "victim": "bundled:classifier-v3"}
    (tmp_path / "good.yaml").write_text(yaml.safe_dump(good))
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({**good, "bogus": 1}))
    (tmp_path / "unknown.yaml").write_text(yaml.safe_dump({**good, "conditions": {
        "grid": {"environment.weather": ["clear", "snow"]}, "holdout": ["weather_fog"]}}))
    (tmp_path / "sweep.yaml").write_text(yaml.safe_dump({"name": "seeds", "run": "bad.yaml", "grid": {"seed": [0, 1]}}))
    (tmp_path / "theirs").mkdir()
    (tmp_path / "theirs" / "notes.txt").write_text("a user's file")
    args = [a.format(bad=tmp_path / "bad.yaml", good=tmp_path / "good.yaml", sweep=tmp_path / "sweep.yaml",
                     unknown=tmp_path / "unknown.yaml", tmp=tmp_path) for a in command]
    out = subprocess.run([sys.executable, "-c", _REFUSED, *args], cwd=ROOT, capture_output=True, text=True)
    assert out.stdout.split("\n")[0] == "2 []", (out.stdout, out.stderr)
    assert len(out.stderr.strip().splitlines()) == 1 and says in out.stderr, out.stderr
    assert (tmp_path / "theirs" / "notes.txt").read_text() == "a user's file"
