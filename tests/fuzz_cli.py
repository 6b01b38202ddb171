"""Generated command lines, and what every ``undream`` command does with them.

A careless user's command line: any command, its arguments and options in
any order, with values drawn from the things a user has lying around (their
thesis folder, the spec, a run config, a scene directory, an earlier run's
output, a file where a folder belongs, ``/proc``, an empty string, numbers
of every size) and from malformed inputs. Each command line runs in-process
through click's test runner against a sandbox folder (:class:`Sandbox`),
and :func:`judge` says what happened:

- exit 0 is allowed (a command may well work), but the user's own files —
  the thesis folder and every input file — are byte-identical afterwards;
- anything else is one line on stderr (``undream: error: …``), exit 2, no
  traceback, and the whole sandbox byte-identical (a refused command changes
  nothing on disk).

The farm's commands get an unreachable broker and a SQLite database in the
sandbox; ``worker`` and ``dashboard`` (which serve until stopped) are left
out. Used by ``tests/test_fuzz_inputs.py`` and ``scripts/fuzz_inputs.py``.
"""
from __future__ import annotations

import hashlib
import json
import os
import stat
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
from hypothesis import strategies as st

# Commands that serve until stopped (or start a worker) are not fuzzed.
LEFT_OUT = {"worker", "dashboard"}
FARM = ["--broker", "redis://127.0.0.1:1/0", "--database", "sqlite:///{root}/farm/undream.db",
        "--blobs", "{root}/farm/blobs"]


# SQLite's own shared-memory and write-ahead files, which any reader of a WAL database may create.
SQLITE_TRANSIENT = ("-shm", "-wal")


def fingerprint(folder: Path) -> dict[str, str]:
    """Every file, folder and link under ``folder``: a file's SHA-256, ``dir``, the link's target, or
    the kind of a special file (a FIFO is never opened: reading it would wait for a writer)."""
    out: dict[str, str] = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            key = str(p.relative_to(folder))
            mode = p.lstat().st_mode
            if stat.S_ISLNK(mode):
                out[key] = f"link -> {os.readlink(p)}"
            elif stat.S_ISDIR(mode):
                out[key] = "dir"
            elif stat.S_ISREG(mode):
                out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[key] = f"special {stat.S_IFMT(mode):o}"
    return out


def changed(before: dict[str, str], after: dict[str, str], under: tuple[str, ...] = ("",)) -> list[str]:
    """Paths that appeared, vanished or changed between two fingerprints, among those under ``under``."""
    keys = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}
    return sorted(k for k in keys if any(k == u or k.startswith(u) for u in under))


@dataclass
class Sandbox:
    """A folder of the things a user has: inputs the commands read and folders they may write."""

    root: Path
    protected: tuple[str, ...]  # a user's own files: never changed by any command, successful or not
    words: dict[str, list[str]]  # value pools by kind: "path", "file", "number", "text", "id"


def make_sandbox(root: Path, spec: dict[str, Any], run: dict[str, Any], scene: Path) -> Sandbox:
    """Write the sandbox under ``root``: ``thesis/`` (a user's folder), ``inputs/`` (a valid spec, a
    valid one-step run config on a copy of ``scene``, a broken one, a sweep, a settings file),
    ``earlier/`` (a folder marked as an earlier run's output), a file where a folder belongs."""
    import shutil

    import yaml

    scene = Path(shutil.copytree(scene, root / "scene"))
    run = {**run, "attack": {"name": "pgd", "eps": 8, "steps": 1}, "sim_spp": 1, "grad_spp": 1, "eval_spp": 1}
    inputs, thesis = root / "inputs", root / "thesis"
    inputs.mkdir(parents=True)
    thesis.mkdir()
    (thesis / "thesis.tex").write_text("years of work\n")
    (thesis / "data.csv").write_text("1,2,3\n")
    (thesis / "results.json").write_text('{"mine": true}\n')
    (inputs / "spec.yaml").write_text(yaml.safe_dump(spec))
    (inputs / "run.yaml").write_text(yaml.safe_dump({**run, "scene": str(scene)}))
    (inputs / "run_bad.yaml").write_text(yaml.safe_dump({**run, "scene": str(scene),
                                                         "attack": {"name": "pgd", "eps": 300}}))
    (inputs / "dup.yaml").write_text(yaml.safe_dump({**run, "scene": str(scene)}) + "seed: 7\nseed: 8\n")
    (inputs / "sweep.yaml").write_text(yaml.safe_dump({"name": "fz", "run": "run.yaml",
                                                        "grid": {"attack.eps": [4, 8]}}))
    (inputs / "settings.yaml").write_text(yaml.safe_dump({"broker_url": "redis://127.0.0.1:1/0"}))
    (inputs / "binary.bin").write_bytes(bytes(range(256)))
    (inputs / "notes.txt").write_text("not a folder\n")
    _farm_database(root / "farm")
    earlier = root / "earlier"
    earlier.mkdir()
    (earlier / "metadata.json").write_text(json.dumps({"undream_output": "run", "status": "started"}))
    r = str(root)
    paths = [str(thesis), f"{r}/inputs", str(scene), str(earlier), f"{r}/new", f"{r}/new/deeper",
             f"{r}/inputs/notes.txt", f"{r}/inputs/notes.txt/below", f"{r}/thesis/sub", "/proc/1/undream",
             "", "-", "a" * 300, f"{r}/{'b' * 300}", r, f"{r}/inputs/spec.yaml"]
    files = [f"{r}/inputs/{n}" for n in ("spec.yaml", "run.yaml", "run_bad.yaml", "dup.yaml", "sweep.yaml",
                                          "settings.yaml", "binary.bin", "notes.txt")]
    files += [f"{r}/missing.yaml", str(thesis / "thesis.tex"), str(scene / "sequence.json")]
    numbers = ["0", "1", "-1", "2", "16", str(10**7), str(2**64), "1" * 5000, "1e308", "nan", "inf", "0.5", "x"]
    text = ["", " ", "é≈∂", "--", "builtin:nope", "bundled:classifier", "classifier", "ab12",
            "postgresql://u:p@127.0.0.1:1/x", "redis://127.0.0.1:1/0", "sqlite:////proc/1/x.db"]
    return Sandbox(root, ("thesis", "inputs"),
                   {"path": paths, "file": files, "number": numbers, "text": text, "id": ["ab12", "fz", ""]})


def _farm_database(folder: Path) -> None:
    """A farm database with one sweep (``fz``) and no runs, for the read-only commands to read."""
    from undream.store import open_store

    store = open_store(f"sqlite:///{folder / 'undream.db'}", folder / "blobs")
    store.create_sweep("fz", {"name": "fz", "grid": {}})
    store.close()


def sandbox_env(box: Sandbox) -> dict[str, str]:
    """The environment of every fuzzed command: the farm's settings point into the sandbox, with a
    broker that nothing answers (nothing is ever queued on the real one)."""
    return {"UNDREAM_BROKER_URL": "redis://127.0.0.1:1/0",
            "UNDREAM_DATABASE_URL": f"sqlite:///{box.root}/farm/undream.db",
            "UNDREAM_BLOB_URL": f"{box.root}/farm/blobs", "UNDREAM_SETTINGS": ""}


def commands(group: click.Group, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], click.Command]:
    """Every leaf command of ``group`` by its path (``("victims", "train")``), less :data:`LEFT_OUT`."""
    out: dict[tuple[str, ...], click.Command] = {}
    for name, cmd in sorted(group.commands.items()):
        if name in LEFT_OUT:
            continue
        if isinstance(cmd, click.Group):
            out.update(commands(cmd, prefix + (name,)))
        else:
            out[prefix + (name,)] = cmd
    return out


def _pool(param: click.Parameter) -> str:
    """The value pool of ``param``: numbers for numeric types, files for arguments, paths for paths."""
    kind = param.type
    if isinstance(kind, (click.types.IntParamType, click.types.FloatParamType, click.IntRange, click.FloatRange)):
        return "number"
    if isinstance(param, click.Argument):
        return "file" if "yaml" in (param.name or "") or param.name in ("spec", "data") else "id"
    if isinstance(kind, click.Path):
        return "path"
    return "text"


@st.composite
def command_lines(draw: Any, box: Sandbox, group: click.Group) -> list[str]:
    """One command line: a command, its arguments, then up to five of its options (or unknown ones)."""
    table = commands(group)
    path = draw(st.sampled_from(sorted(table)))
    cmd = table[path]
    argv = list(path)
    any_value = st.sampled_from(sorted({w for ws in box.words.values() for w in ws}))
    for param in cmd.params:
        if isinstance(param, click.Argument):
            pool = box.words[_pool(param)]
            argv.append(draw(st.one_of(st.sampled_from(pool), any_value) if draw(st.booleans()) else
                             st.sampled_from(pool)))
    options = [p for p in cmd.params if isinstance(p, click.Option) and "--help" not in p.opts]
    for _ in range(draw(st.integers(0, 5))):
        if not options or draw(st.integers(0, 9)) == 0:
            argv += [draw(st.sampled_from(["--bogus", "--out", "--force", "--check", "-x"]))]
            continue
        opt = draw(st.sampled_from(options))
        flag = draw(st.sampled_from(opt.opts + opt.secondary_opts))
        argv.append(flag)
        if not opt.is_flag and flag not in opt.secondary_opts:
            choices = getattr(opt.type, "choices", None)
            pool = [str(c) for c in choices] if choices else box.words[_pool(opt)]
            argv.append(draw(st.sampled_from(pool) if draw(st.integers(0, 3)) else any_value))
    if path[0] in ("status", "results", "cancel", "resume", "submit", "sweep", "report") and draw(st.booleans()):
        argv += [a.format(root=box.root) for a in FARM]
    return argv


def judge(argv: list[str], box: Sandbox, runner: Any) -> str:
    """Run ``argv`` in ``box``; ``ok`` / ``refused`` or ``FAIL: why`` (see the module docstring)."""
    from undream.cli import main

    before = fingerprint(box.root)
    cwd = os.getcwd()
    os.chdir(box.root)  # relative paths land in the sandbox, where they are seen
    try:
        result = runner.invoke(main, argv, catch_exceptions=True, prog_name="undream")
    finally:
        os.chdir(cwd)
    after = fingerprint(box.root)
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        tb = "".join(traceback.format_exception(result.exception)[-4:])
        return f"FAIL: traceback {type(result.exception).__name__}: {result.exception}\n{tb}"
    harmed = changed(before, after, box.protected)
    if harmed:
        return f"FAIL: exit {result.exit_code} changed the user's files: {harmed[:5]}"
    if result.exit_code == 0:
        return "ok"
    lines = result.stderr.strip().splitlines()
    if result.exit_code != 2 or len(lines) != 1 or not lines[0].startswith("undream: error: "):
        return f"FAIL: exit {result.exit_code}, {len(lines)} line(s): {result.stderr[-2000:]!r}"
    left = [k for k in changed(before, after) if not k.endswith(SQLITE_TRANSIENT)]
    if left:
        return f"FAIL: refused ({lines[0]}) but changed the disk: {left[:5]}"
    return "refused"
