"""Before ``undream run`` writes or deletes anything: validate the whole run, and the output folder rule.

:func:`preflight` checks what can be checked without rendering, in order of
cost: the attack block, the simulator (``sim: blender`` needs Blender's
Python), the store URL, the scene source (a scene directory's
``sequence.json`` or a spec file, parsed), the victim (loaded) and its labels.
:func:`check_output_folder` then says whether ``--out`` may be used:
``--force`` only ever replaces a folder that ``undream run`` created
(recognised by its ``metadata.json``, written when the run starts and again
with the results), and never one that holds the run's own scene or spec.
"""
from __future__ import annotations

import contextlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from undream.errors import SpecError, StoreError, UndreamError, already_exists
from undream.printing.profiles import resolve_gamut
from undream.redact import MASK, redact
from undream.render.budget import run_estimate
from undream.scenedir.conditions import conditions_sequence
from undream.scenedir.init import InitOptions, check_source
from undream.scenedir.verify import check_seen
from undream.settings import LocalSettings
from undream.sim import check_simulator
from undream.spec import load_sequence
from undream.spec.io import check_writable_target, resolve_against
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from undream.render.budget import Estimate
    from undream.spec import Sequence
    from undream.victims import Victim

METADATA = "metadata.json"
MARKER = "undream_output"  # key of the metadata.json written when a run starts


def scene_source(config: RunConfig, base_dir: Path) -> Path:
    """The run's scene as the user named it: a scene directory or a spec file (absolute)."""
    return Path(resolve_against(config.scene, base_dir))


def scene_sources(config: RunConfig, base_dir: Path) -> list[Path]:
    """Every scene the run names: :func:`scene_source` and a multi-condition run's ``conditions.scenes``."""
    more = config.conditions.scenes if config.conditions is not None else ()
    return [scene_source(config, base_dir)] + [Path(resolve_against(s, base_dir)) for s in more]


@dataclass(frozen=True)
class Checked:
    """What :func:`preflight` found: the loaded victim, the sequence and the run's estimate."""

    victim: "Victim"
    sequence: "Sequence"
    estimate: "Estimate"


def preflight(config: RunConfig, base_dir: Path, source: str | Path | None = None,
              local: LocalSettings = LocalSettings()) -> Checked:
    """Validate everything a run needs that rendering does not, cheapest first.

    The attack, the store URL, the scene (a spec file gets every check of
    ``undream init``: meshes with UVs, the texture, its verification renders'
    memory), the frames per step, the renders' memory (:mod:`undream.render.budget`),
    then the victim (loaded) and its labels. ``source``: the run config's
    file, named at the start of every error. ``local``: this process's settings,
    read at the edge (Blender's interpreter, Unreal's spool, the memory limit, the hub).
    """
    if source is None:
        return _preflight(config, base_dir, local)
    try:
        return _preflight(config, base_dir, local)
    except StoreError:
        raise
    except UndreamError as err:
        raise type(err)(f"{source}: {err}") from None


def _preflight(config: RunConfig, base_dir: Path, local: LocalSettings) -> Checked:
    check_simulator(config.sim, local)
    resolve_gamut(config.gamut, local.undream_cache)  # the printer's profile is there and a CMYK one
    if config.store:
        from undream.store.db import check_database

        check_database(config.store)  # reachable, and a database: before anything is written
    if config.conditions is not None:
        # what `undream init` checks before writing OUT/scene, on every condition's frames
        seq = check_source(conditions_sequence(config, base_dir, local.undream_cache),
                           InitOptions(memory_limit=local.memory_limit, cache_dir=local.undream_cache)).sequence
    else:
        seq = _sequence(scene_source(config, base_dir), local.memory_limit, local.undream_cache)
    check_frames(config, seq)
    estimate = run_estimate(seq, config, limit=local.memory_limit)
    # torch from here on: a run refused for its scene, conditions or frames was refused without it
    from undream.attacks import make_attack
    from undream.engine.context import class_ids, task_of
    from undream.victims import load_victim

    make_attack(config.attack)
    victim = load_victim(config.victim, device=config.device, task=task_of(config), offline=local.hf_offline,
                         cache_home=local.cache_home)
    class_ids(config, seq, victim)
    return Checked(victim, seq, estimate)


def check_frames(config: RunConfig, sequence: "Sequence") -> None:
    """The held-out split fits the sequence, and ``frames_per_step`` the frames left to attack."""
    attacked, held = config.split(sequence)
    per_step = config.attack.frames_per_step
    if per_step is not None and per_step > len(attacked):
        raise SpecError(f"attack.frames_per_step: {per_step} is more than the {len(attacked)} frames left "
                        f"to attack (the sequence's {len(sequence.frames)} frames, {len(held)} held out)")


def _sequence(src: Path, memory_limit: int | None = None, cache_dir: str | None = None) -> "Sequence":
    if is_scene(src):
        seq = load_sequence(src / SCENE_MARKER)
        check_seen(src, seq)  # a spec file: `undream init` checks it (each condition's frames too)
        return seq
    if not src.is_file():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    # what `undream init` checks before writing OUT/scene
    return check_source(src, InitOptions(memory_limit=memory_limit, cache_dir=cache_dir)).sequence


def run_metadata(folder: Path) -> dict | None:
    """The ``metadata.json`` of an output folder of ``undream run`` (written when the run starts,
    replaced when it ends); None when ``folder`` has none that says it is one."""
    try:
        meta = json.loads((Path(folder) / METADATA).read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and (MARKER in meta or "run_id" in meta) else None


def is_run_output(folder: Path) -> bool:
    """Whether ``folder`` is an output folder of ``undream run`` (its ``metadata.json`` says so)."""
    return run_metadata(folder) is not None


def run_store_url(folder: Path) -> str | None:
    """The store URL a run's output folder records (None: the SQLite store inside it; with its
    password masked when it had one)."""
    return ((run_metadata(folder) or {}).get("config") or {}).get("store")


SCENE_MARKER = "sequence.json"  # what `undream init` writes last: a scene directory


def is_scene(folder: Path) -> bool:
    """Whether ``folder`` is a scene directory (``undream init`` wrote its ``sequence.json``)."""
    return (Path(folder) / SCENE_MARKER).is_file()


def check_output_folder(out: Path, scene_src: Path | None, force: bool, command: str = "undream run",
                        marker: str = METADATA, inputs: tuple[Path | None, ...] = ()) -> None:
    """The one output-folder rule of every command that writes: refuse an ``--out`` that must not be
    used, in one line; nothing is touched.

    ``out`` may be written when it is absent or empty. It is replaced (``force``) only when
    ``command`` wrote it (``marker``: ``undream run``'s run metadata unless another command names
    its own file, :data:`SCENE_MARKER` for ``undream init``'s scenes), when no
    live process holds the lease of a run recorded in it (:func:`live_owner`), and when it holds
    none of the command's inputs (``scene_src`` and ``inputs``: a spec, a run config, a scene; None
    entries are skipped) —
    so neither a project folder holding them nor the folder of an earlier output is lost.
    """
    out = Path(out).resolve()
    check_writable_target(out)
    named = [(scene_src, "the run's scene")] + [(p, "this command's input") for p in inputs]
    for path, what in ((Path(p).resolve(), what) for p, what in named if p is not None):
        if out == path or out in path.parents:
            raise SpecError(f"--out {out}: holds {what} {path}; choose another output folder")
    if not (out.exists() and any(out.iterdir())):
        return
    if not force:
        raise already_exists(out)
    if marker != SCENE_MARKER and is_scene(out):
        raise SpecError(f"--out {out}: is a scene directory (it holds {SCENE_MARKER}); `{command}` never "
                        "replaces a scene; choose another output folder")
    if not (is_run_output(out) if marker == METADATA else (out / marker).is_file()):
        raise SpecError(f"--out {out}: --force only replaces a folder that `{command}` wrote "
                        f"(one with its {marker}); this one has none, so it is left as it is")
    owner = live_owner(out)
    if owner is not None:
        raise SpecError(f"--out {out}: {owner} is writing it now; wait for it to end (or stop it) "
                        "before replacing the folder")


def check_output_files(outputs: tuple[tuple[str, Path | None], ...], inputs: tuple[Path | None, ...] = ()) -> None:
    """The one rule of a command's output files (``undream evaluate --json/--csv/--frames-csv``,
    ``undream victims evaluate --json``), checked before the command's work: a refusal in one line
    naming the option, nothing written.

    ``outputs`` are (option, path) pairs, None paths skipped. Each must be a file name in a folder
    that exists and can be written, and no two may name the same file. A name that exists must be a
    regular file (a FIFO, a device, a socket or a symbolic link is never replaced by one). It is
    replaced only when it is none of ``inputs`` (the texture, the scenes, the victims, the data, the
    settings file; None entries and names that are no path, a farm run's id or ``bundled:NAME``,
    are skipped), lies in none of the folders among them, and lies in no scene directory or output
    folder of ``undream run``: minutes of renders are not lost to a path that cannot be written, and
    no input or earlier result is overwritten by a swapped argument.
    """
    given = [Path(p).resolve() for p in inputs if p is not None and Path(p).exists()]
    seen: dict[Path, str] = {}
    for option, path in outputs:
        if path is None:
            continue
        target = Path(path).resolve()
        if target in seen:
            raise SpecError(f"{option} {path}: {seen[target]} names the same file; give each output its own")
        seen[target] = option
        _check_output_file(option, Path(path), given)


_NOT_REGULAR = ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                (stat.S_ISSOCK, "a socket"))


def _check_output_file(option: str, path: Path, given: list[Path]) -> None:
    """One output file of :func:`check_output_files`; ``given``: the inputs that exist, resolved."""
    target = path.resolve()
    if target.is_dir():
        raise SpecError(f"{option} {path}: is a folder; give a file name")
    mode = path.lstat().st_mode if os.path.lexists(path) else None
    kind = None if mode is None else next((what for test, what in _NOT_REGULAR if test(mode)), None)
    if kind is not None:
        raise SpecError(f"{option} {path}: is {kind}, not a regular file; it is never replaced, choose another file")
    if not target.parent.is_dir():
        raise SpecError(f"{option} {path}: its folder {target.parent} does not exist")
    check_writable_target(target.parent, option)
    if mode is None:
        return
    for source in given:
        if target == source or source in target.parents:
            where = "is" if target == source else f"lies in {source},"
            raise SpecError(f"{option} {path}: {where} this command's input; choose another file")
    owner = next((d for d in target.parents if is_scene(d) or is_run_output(d)), None)
    if owner is not None:
        kind = "the scene directory" if is_scene(owner) else "the output folder of `undream run`"
        raise SpecError(f"{option} {path}: would replace a file of {kind} {owner}; choose another file")


def live_owner(out: Path) -> str | None:
    """``run ID (host:pid)`` when a run recorded in the store under ``out`` is held by a live process
    (its lease: :func:`scheduler.lease.stale_reason`), else None. A store that cannot be read for
    want of its password counts as live: nothing is replaced that cannot be checked."""
    from scheduler.lease import stale_reason
    from undream.store import open_store
    from undream.store.models import utcnow

    if not (out / "store").is_dir():
        return None
    url = run_store_url(out)
    if url and MASK in url:
        return "a run whose store needs a password this folder does not keep (cannot check its lease)"
    try:
        store = open_store(url, out / "store", create=False)
    except StoreError:
        return None
    try:
        now = utcnow()
        for run in store.owned_runs():
            if stale_reason(run, now) is None:
                return f"run {run.id} ({run.owner}, alive)"
    finally:
        store.close()
    return None


def claim_output(out: Path, config: RunConfig, marker: str = METADATA, command: str = "run") -> None:
    """Make ``out`` this command's output folder, atomically: create it (and its parents) if absent,
    then its starting ``marker`` file exclusively (``O_EXCL``): ``undream run``'s ``metadata.json``, or
    ``baseline.json`` for ``undream baseline`` (``command``, recorded in the file). Of two commands
    given the same new ``--out``, both past :func:`check_output_folder`, one claims it and the other
    gets a one-line SpecError and deletes nothing: the folder and its files are the winner's. A
    failure (a full disk, a signal) while the file is written removes it, and the folder when this
    call made it."""
    out = Path(out)
    for _ in range(3):  # the folder may vanish between mkdir and open: a racing claim that gave it up
        try:
            out.mkdir(parents=True)
            made = True
        except FileExistsError:
            made = False
        try:
            fd = os.open(out / marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            raise _claimed(out, command, marker) from None
        except FileNotFoundError:
            continue
    else:
        raise SpecError(f"--out {out}: other commands made and removed this folder while this {command} claimed "
                        "it; it is left as it is; run the command again")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps({MARKER: command, "status": "started", "config": redact(config.to_json())},
                               indent=1) + "\n")
        # Another command's marker (a run's metadata.json beside a baseline's baseline.json) or files:
        # of two that race, the one that finds the other's file gives the folder up.
        others = sorted(p.name for p in out.iterdir() if p.name != marker)
        if others:
            raise _claimed(out, command, others[0])
    except BaseException:
        (out / marker).unlink(missing_ok=True)
        if made:
            with contextlib.suppress(OSError):  # not empty: another process wrote there meanwhile
                out.rmdir()
        raise


def _claimed(out: Path, command: str, found: str) -> SpecError:
    return SpecError(f"--out {out}: another command claimed this folder after this {command}'s checks (its "
                     f"{found} appeared); it is left as it is; choose another output folder")
