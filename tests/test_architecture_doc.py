"""docs/architecture.md stays true: every module, function, class, method and file it cites exists.

The page names where each stage of Algorithm 1 lives (``scheduler.iteration.reduce_and_step``,
``Store.advance``, ``scheduler/stages.py``, ...); a rename that forgets the page fails here, naming
the stale names.
"""
from __future__ import annotations

import ast
import re
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
PACKAGES = ("undream", "scheduler", "workers")
CODE = re.compile(r"`([^`\n]+)`")
DOTTED = re.compile(r"^(?:undream|scheduler|workers)(?:\.[A-Za-z_][A-Za-z0-9_]*)+$")
METHOD = re.compile(r"^([A-Z][A-Za-z0-9]+)\.([a-z_][A-Za-z0-9_]*)$")  # Store.advance, Attack.step
TASK_NAMES = {"undream.start", "undream.frames", "undream.collect"}  # Celery task names, not modules
FILE = re.compile(r"^[\w./-]+\.(?:py|md|toml|yaml|yml|sh)$")


def _cited() -> set[str]:
    names = set()
    for span in CODE.findall(PAGE.read_text(encoding="utf-8")):
        for word in re.split(r"[\s,()→]+", span):
            word = word.strip(":;").removesuffix("()")
            if DOTTED.match(word) or METHOD.match(word) or FILE.match(word):
                names.add(word)
    return names


def _module_file(parts: list[str]) -> Path | None:
    base = ROOT.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _top_names(path: Path) -> set[str]:
    """What a module defines or imports at its top level (names its readers can reach)."""
    names = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


@lru_cache(maxsize=1)
def _classes() -> dict[str, tuple[set[str], list[str]]]:
    """Class name → (the names defined in its body, its bases' names), over the packages' modules."""
    found: dict[str, tuple[set[str], list[str]]] = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ClassDef):
                    body, bases = found.setdefault(node.name, (set(), []))
                    bases.extend(b.id for b in node.bases if isinstance(b, ast.Name))
                    for item in node.body:
                        if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                            body.add(item.name)
                        elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                            body.add(item.target.id)
                        elif isinstance(item, ast.Assign):
                            body.update(t.id for t in item.targets if isinstance(t, ast.Name))
    return found


def _has_member(cls: str, attr: str, seen: frozenset[str] = frozenset()) -> bool:
    members, bases = _classes().get(cls, (set(), []))
    return attr in members or any(_has_member(b, attr, seen | {cls}) for b in bases if b not in seen)


def _resolves(name: str) -> bool:
    """``a.b.c``: a module or package on disk, then a name it defines, then (for a class) a member of
    it or of its bases. Read from the source, so modules that need Blender or a GPU count too."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        path = _module_file(parts[:cut])
        if path is None:
            continue
        rest = parts[cut:]
        if not rest:
            return True
        if rest[0] not in _top_names(path):
            return False
        return all(_has_member(rest[i], rest[i + 1]) for i in range(len(rest) - 1))
    return False


def _file_exists(name: str) -> bool:
    if (ROOT / name).exists() or (ROOT / "docs" / name).exists():
        return True
    return any(p.as_posix().endswith("/" + name) for p in ROOT.glob(f"**/{Path(name).name}")
               if ".venv" not in p.parts and "build" not in p.parts)


def test_the_page_cites_the_stages_of_algorithm_1():
    cited = _cited()
    for stage in ("scheduler.iteration.frame_jobs", "undream.engine.job.render_and_grad_many",
                  "scheduler.iteration.reduce_and_step", "Store.advance"):
        assert stage in cited, stage


def test_every_name_the_architecture_page_cites_exists():
    stale = []
    for name in sorted(_cited()):
        if name in TASK_NAMES:
            ok = f'"{name}"' in (ROOT / "workers" / "tasks.py").read_text(encoding="utf-8")
        elif DOTTED.match(name):
            ok = _resolves(name)
        elif METHOD.match(name):
            ok = _has_member(*METHOD.match(name).groups())
        else:
            ok = _file_exists(name)
        if not ok:
            stale.append(name)
    assert not stale, f"docs/architecture.md cites names that do not exist: {', '.join(stale)}"
