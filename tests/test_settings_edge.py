"""Settings are read at the edge (issue 20): the environment is consulted in ``undream/settings.py``,
``undream/cli/`` and ``workers/`` only, and passed down as parameters.

The AST check walks every ``.py`` file of ``undream/``, ``scheduler/`` and ``workers/`` and names
``file:line`` for each use of ``os.environ``, ``os.getenv``, ``os.putenv`` or ``os.unsetenv``
(however ``os`` or the name was imported) where it is not allowed; ``workers/`` may read the
environment but never write it. The user's path is checked too: variables given in the environment
of an ``undream`` subprocess still change what the command does.
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("undream", "scheduler", "workers")
NAMES = {"environ", "getenv", "putenv", "unsetenv", "environb", "getenvb"}
WRITES = {"putenv", "unsetenv"}  # os functions that change the environment
MUTATORS = {"setdefault", "update", "pop", "popitem", "clear", "__setitem__", "__delitem__"}
# Where the environment may be read (and written: only the CLI, which configures other libraries
# for its own process, e.g. HF_HUB_DISABLE_PROGRESS_BARS). No other exceptions.
MAY_READ = ("undream/settings.py", "undream/cli/", "workers/")
MAY_WRITE = ("undream/settings.py", "undream/cli/")


def _env_uses(tree: ast.AST) -> list[tuple[int, str, bool]]:
    """(line, what, writes) for every use of the process environment in ``tree``."""
    aliases = {"os"}  # names bound to the os module
    direct: set[str] = set()  # names bound to os.environ / os.getenv / ... themselves
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            aliases |= {a.asname or a.name for a in node.names if a.name == "os"}
        elif isinstance(node, ast.ImportFrom) and node.module == "os":
            direct |= {a.asname or a.name for a in node.names if a.name in NAMES}
    parents = {child: parent for parent in ast.walk(tree) for child in ast.iter_child_nodes(parent)}
    uses = []
    for node in ast.walk(tree):
        name = None
        if isinstance(node, ast.Attribute) and node.attr in NAMES and isinstance(node.value, ast.Name) \
                and node.value.id in aliases:
            name = f"{node.value.id}.{node.attr}"
        elif isinstance(node, ast.Name) and node.id in direct:
            name = node.id
        if name is None:
            continue
        parent = parents.get(node)
        writes = name.rsplit(".", 1)[-1] in WRITES
        if isinstance(parent, ast.Attribute) and parent.attr in MUTATORS:
            writes = True
        if isinstance(parent, ast.Subscript) and isinstance(parent.ctx, (ast.Store, ast.Del)):
            writes = True
        uses.append((node.lineno, name, writes))
    return uses


def offending_env_uses(root: Path = ROOT) -> list[str]:
    """``path:line: what`` for each use of the environment below the edge."""
    bad = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            for line, what, writes in _env_uses(ast.parse(path.read_text(), rel)):
                allowed = MAY_WRITE if writes else MAY_READ
                if not rel.startswith(allowed):
                    bad.append(f"{rel}:{line}: {what} {'written' if writes else 'read'} "
                               f"outside {', '.join(allowed)}")
    return bad


def test_the_environment_is_read_at_the_edge_only():
    bad = offending_env_uses()
    assert not bad, "read settings in undream/settings.py (load_local) and pass them down:\n" + "\n".join(bad)


@pytest.mark.parametrize(("rel", "code", "expect"), [
    ("undream/render/foo.py", 'import os\nX = os.environ.get("X")\n', "undream/render/foo.py:2: os.environ read"),
    ("scheduler/foo.py", "from os import getenv as g\n\n\ndef f():\n    return g('X')\n",
     "scheduler/foo.py:5: g read"),
    ("workers/foo.py", "import os as o\no.environ['X'] = '1'\n", "workers/foo.py:2: o.environ written"),
    ("workers/bar.py", "import os\nos.environ.setdefault('X', '1')\n", "workers/bar.py:2: os.environ written"),
    ("undream/variant2.py", "import os\nos.putenv('X', '1')\n", "undream/variant2.py:2: os.putenv written"),
])
def test_the_check_names_file_and_line(tmp_path, rel, code, expect):
    """A planted use below the edge is found (the check cannot pass vacuously); reads in workers/,
    undream/cli/ and undream/settings.py are not."""
    for package in PACKAGES:
        (tmp_path / package).mkdir()
    (tmp_path / "workers" / "ok.py").write_text("import os\nN = os.environ.get('N')\n")
    (tmp_path / "undream" / "settings.py").write_text("import os\nos.environ.setdefault('N', '1')\n")
    target = tmp_path / rel
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(code)
    bad = offending_env_uses(tmp_path)
    assert len(bad) == 1 and bad[0].startswith(expect), bad


# --- through the command line ------------------------------------------------------------------------

def _undream(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if not k.startswith("UNDREAM_")}
    return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env={**base, **env}, timeout=300)


@pytest.fixture(scope="module")
def run_yaml(tmp_path_factory) -> Path:
    """A small run of the bundled classifier on the example scene spec (nothing renders under --check)."""
    from farm_support import make_victim

    tmp = tmp_path_factory.mktemp("edge")
    run = tmp / "run.yaml"
    run.write_text(yaml.safe_dump({"scene": str(ROOT / "examples" / "bin_park.yaml"),
                                   "victim": make_victim(tmp / "victim"), "loss": "ce",
                                   "attack": {"name": "pgd", "eps": 8, "steps": 1},
                                   "sim_spp": 1, "grad_spp": 1, "eval_spp": 1}))
    return run


def test_the_memory_limit_in_the_environment_changes_run_check(run_yaml):
    ok = _undream(["run", str(run_yaml), "--out", str(run_yaml.parent / "out"), "--check"], {}, run_yaml.parent)
    assert ok.returncode == 0 and "nothing written" in ok.stdout, ok.stderr
    small = _undream(["run", str(run_yaml), "--out", str(run_yaml.parent / "out"), "--check"],
                     {"UNDREAM_MEMORY_LIMIT": "1M"}, run_yaml.parent)
    lines = small.stderr.strip().splitlines()
    assert small.returncode == 2 and len(lines) == 1, small.stderr
    assert "run.yaml" in lines[0] and "1.05 MB is available" in lines[0] and "UNDREAM_MEMORY_LIMIT" in lines[0]
    bad = _undream(["run", str(run_yaml), "--out", str(run_yaml.parent / "out"), "--check"],
                   {"UNDREAM_MEMORY_LIMIT": "lots"}, run_yaml.parent)
    assert bad.returncode == 2 and "UNDREAM_MEMORY_LIMIT: 'lots' is not a size" in bad.stderr
    assert not (run_yaml.parent / "out").exists()


def test_the_mitsuba_variant_in_the_environment_changes_run_check(run_yaml):
    res = _undream(["run", str(run_yaml), "--out", str(run_yaml.parent / "out"), "--check"],
                   {"UNDREAM_MI_VARIANT": "no_such_variant"}, run_yaml.parent)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "no usable Mitsuba variant (no_such_variant: not compiled in this mitsuba build)" in lines[0]
    assert not (run_yaml.parent / "out").exists()


def test_the_unreal_spool_in_the_environment_reaches_run_check(run_yaml, tmp_path):
    """``sim: unreal``: the spool folder comes from UNDREAM_UNREAL_SPOOL given to the command."""
    config = yaml.safe_load(run_yaml.read_text())
    run = tmp_path / "run.yaml"
    run.write_text(yaml.safe_dump({**config, "sim": "unreal"}))
    missing = _undream(["run", str(run), "--out", str(tmp_path / "out"), "--check"],
                       {"UNDREAM_UNREAL_SPOOL": str(tmp_path / "nowhere")}, tmp_path)
    assert missing.returncode == 2 and f"spool folder {tmp_path / 'nowhere'} not found" in missing.stderr
    (tmp_path / "spool").mkdir()
    ok = _undream(["run", str(run), "--out", str(tmp_path / "out"), "--check"],
                  {"UNDREAM_UNREAL_SPOOL": str(tmp_path / "spool")}, tmp_path)
    assert ok.returncode == 0 and "nothing written" in ok.stdout, ok.stderr


def test_local_settings_from_the_environment():
    from undream.settings import LocalSettings, SettingsError, load_local

    assert load_local({}) == LocalSettings(cache_home=str(Path.home() / ".cache"))
    local = load_local({"UNDREAM_MI_VARIANT": "llvm_ad_rgb", "UNDREAM_FROZEN": "0", "UNDREAM_MEMORY_LIMIT": "2G",
                        "UNDREAM_BLENDER_PYTHON": "/opt/py", "UNDREAM_BLENDER_THREADS": "3",
                        "UNDREAM_UNREAL_SPOOL": "/spool", "UNDREAM_UNREAL_TIMEOUT": "30",
                        "HF_HUB_OFFLINE": "1", "XDG_CACHE_HOME": "/c"})
    assert (local.mi_variant, local.frozen, local.memory_limit, local.blender_python, local.blender_threads,
            local.unreal_spool, local.unreal_timeout_s, local.hf_offline, local.cache_home) == \
        ("llvm_ad_rgb", False, 2 << 30, "/opt/py", 3, "/spool", 30.0, True, "/c")
    assert local.child_env is not None and local.child_env["XDG_CACHE_HOME"] == "/c"
    assert "child_env" not in repr(local)
    with pytest.raises(SettingsError, match="UNDREAM_BLENDER_THREADS: must be a whole number"):
        load_local({"UNDREAM_BLENDER_THREADS": "many"})
