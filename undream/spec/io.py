"""Reading spec files (JSON, YAML), writing the canonical ``sequence.json``, checking an output folder;
paths relative to a spec's folder; writing a file atomically.

Errors are one :class:`~undream.errors.SpecError` line naming the file (and
the line of a syntax error), whichever reader finds them.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import secrets
import shutil
from pathlib import Path
from typing import IO, Any, Callable, Iterator

from undream.errors import SpecError
from undream.spec.limits import FILE_LIMITS
from undream.spec.model import Sequence


def _text(path: Path, most: int) -> str:
    """The UTF-8 text of ``path``, refused unread when it is larger than ``most`` bytes."""
    try:
        if not path.is_file():
            raise SpecError(f"{path}: file not found")
        size = path.stat().st_size
    except OSError as err:
        raise SpecError(f"{path}: cannot read ({err.strerror})") from None
    if size > most:
        raise SpecError(f"{path}: {size} bytes; an input file may hold at most {most} bytes")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise SpecError(f"{path}: not a text file (byte 0x{err.object[err.start]:02x} at offset {err.start} "
                        "is not UTF-8)") from None
    except OSError as err:
        raise SpecError(f"{path}: cannot read ({err.strerror})") from None


def _line_of(text: str, needle: str, nth: int = 0) -> int:
    """The 1-based line of the ``nth`` occurrence of ``needle`` in ``text`` (0 if absent)."""
    at = -1
    for _ in range(nth + 1):
        at = text.find(needle, at + 1)
        if at < 0:
            return 0
    return text.count("\n", 0, at) + 1


def _json_depth(text: str) -> int:
    """How deeply the arrays and objects of JSON ``text`` nest (strings skipped), without recursion."""
    import numpy as np  # here, not at the top: `import undream.spec` stays ~20 ms without numpy

    bare = re.sub(r'"(?:[^"\\]|\\.)*"', '""', text).encode("utf-8", "replace")
    codes = np.frombuffer(bare, np.uint8)
    steps = (codes == ord("[")).astype(np.int32) + (codes == ord("{")) - (codes == ord("]")) - (codes == ord("}"))
    return int(np.cumsum(steps).max(initial=0))


class _DuplicateKey(ValueError):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def read_json(path: str | Path) -> Any:
    """The parsed content of a JSON file, under :data:`undream.spec.limits.FILE_LIMITS`: size, depth,
    digits of a number; a key given twice in one object is refused (naming it and its line)."""
    path = Path(path)
    text = _text(path, FILE_LIMITS["json_bytes"])
    if _json_depth(text) > FILE_LIMITS["depth"]:
        raise SpecError(f"{path}: nested deeper than {FILE_LIMITS['depth']} levels of arrays and objects")

    def number(kind: type) -> Any:
        def parse(s: str) -> Any:
            if sum(ch.isdigit() for ch in s) > FILE_LIMITS["digits"]:
                raise SpecError(f"{path}: line {_line_of(text, s)}: a number of {len(s)} digits is not a number "
                                f"in range (at most {FILE_LIMITS['digits']} digits)")
            return kind(s)
        return parse

    try:
        return json.loads(text, object_pairs_hook=_no_duplicates, parse_int=number(int), parse_float=number(float))
    except _DuplicateKey as err:
        key = err.args[0]
        raise SpecError(f"{path}: duplicate key {key!r} at line {_line_of(text, json.dumps(key), 1)} "
                        f"(first at line {_line_of(text, json.dumps(key))})") from None
    except json.JSONDecodeError as err:
        raise SpecError(f"{path}: line {err.lineno} column {err.colno}: not valid JSON ({err.msg})") from None
    except RecursionError:
        raise SpecError(f"{path}: nested deeper than {FILE_LIMITS['depth']} levels of arrays and objects") from None


def read_yaml(path: str | Path) -> Any:
    """The parsed content of a YAML file (safe types only), under :data:`undream.spec.limits.FILE_LIMITS`:
    size, nesting depth, values after alias expansion, digits of a number; a key given twice in one
    mapping is refused, naming it and both lines. Each refusal is one :class:`SpecError` line."""
    import yaml  # here, with yaml_strict: yaml loads only when a YAML file is read

    from undream.spec.yaml_strict import load

    path = Path(path)
    text = _text(path, FILE_LIMITS["yaml_bytes"])
    try:
        return load(text)
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise SpecError(f"{path}: not valid YAML{line}") from None


def load_sequence(path: str | Path) -> Sequence:
    """Parse a canonical ``sequence.json``; errors name the file and the field."""
    data = read_json(path)
    try:
        return Sequence.from_json(data)
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None


def save_sequence(seq: Sequence, path: str | Path) -> None:
    """Write ``seq`` as canonical JSON (the exact inverse of :func:`load_sequence`)."""
    with naming(path):
        Path(path).write_text(json.dumps(seq.to_json(), indent=1) + "\n")


def join_against(path: str | Path, base_dir: str | Path | None) -> Path:
    """``path`` joined to ``base_dir`` (the spec's folder) when it is relative; as given when it is
    absolute or ``base_dir`` is None. Not resolved: see :func:`resolve_against`."""
    p = Path(path)
    return p if p.is_absolute() or base_dir is None else Path(base_dir) / p


def resolve_against(path: str | Path, base_dir: str | Path | None, *, keep_absolute: bool = False) -> str:
    """``path`` as an absolute path: a relative one against ``base_dir`` (the spec's folder; the
    working directory when None), resolved. ``keep_absolute``: an absolute ``path`` is returned as
    given (``str(path)``), not resolved."""
    if keep_absolute and Path(path).is_absolute():
        return str(path)
    return str(join_against(path, base_dir).resolve())


# How Mitsuba's writers (Bitmap.write, Mesh.write_ply) say the disk is full: a RuntimeError
# ``[FileStream] "PATH": I/O error while attempting to write N bytes: No space left on device``.
_FULL_DISK_TEXTS = {errno.ENOSPC: "No space left on device", errno.EDQUOT: "Disk quota exceeded"}


@contextlib.contextmanager
def naming(path: str | Path) -> Iterator[None]:
    """Name ``path`` in a write's error that names no file: ``write()`` and ``close()`` on a full disk
    raise ``OSError(ENOSPC)`` with no file name, and Mitsuba's writers a RuntimeError; both become an
    ``OSError`` whose ``filename`` is ``path``, which the command line prints as one line
    (:func:`undream.cli.errors.one_line_errors`). Other exceptions pass unchanged."""
    try:
        yield
    except OSError as err:
        if err.filename is not None:
            raise
        raise OSError(err.errno, err.strerror or str(err), str(path)) from err
    except RuntimeError as err:
        code = next((c for c, text in _FULL_DISK_TEXTS.items() if text in str(err)), None)
        if code is None:
            raise
        raise OSError(code, _FULL_DISK_TEXTS[code], str(path)) from err


def atomic_write(path: str | Path, data: bytes | str | Callable[[IO[bytes]], Any], *, fsync: bool = False,
                 mode: int = 0o666) -> int:
    """Write ``path`` so that a reader sees its old content or the new, never part of either.

    ``data``: bytes, text (written as UTF-8) or a writer called with the open binary file. It goes
    into a new hidden sibling (``.NAME.<random>.tmp``), is flushed (and with ``fsync``, forced to
    disk), then renamed over ``path`` (``os.replace``). Whatever fails, even the writer, the
    temporary file is removed, ``path`` is left as it was and the exception propagates. ``mode``:
    the new file's permission bits, before the umask. Returns the bytes written. An error that names
    no file (a full disk) names ``path`` (:func:`naming`).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with naming(path), os.fdopen(fd, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode("utf-8") if isinstance(data, str) else data)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
            size = f.tell()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return size


# Kernel file systems that show the machine's state: nothing undream writes can live there.
PSEUDO_FILESYSTEMS = {"proc", "sysfs", "devtmpfs", "devpts", "cgroup", "cgroup2", "securityfs", "debugfs",
                      "tracefs", "configfs", "pstore", "bpf", "mqueue", "hugetlbfs", "fusectl", "binfmt_misc"}


def _filesystem(folder: Path) -> str | None:
    """The type of the file system ``folder`` is on (Linux's /proc/self/mounts), None if unknown."""
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return None
    best, kind = "", None
    folder_s = str(folder.resolve())
    for line in mounts:
        parts = line.split()
        if len(parts) < 3:
            continue
        point = parts[1].replace("\\040", " ")
        if (folder_s == point or folder_s.startswith(point.rstrip("/") + "/")) and len(point) >= len(best):
            best, kind = point, parts[2]
    return kind


def check_writable_target(out: str | Path, option: str = "--out") -> None:
    """Refuse an output folder that cannot be created or written, before anything is written.

    One SpecError line naming ``option`` and the folder: a file in the way
    (``out`` itself or a parent), a read-only file system, no write permission.
    """
    out = Path(out).absolute()
    if out.exists() and not out.is_dir():
        raise SpecError(f"{option} {out}: exists and is not a folder")
    existing = next(p for p in (out, *out.parents) if p.exists())
    if not existing.is_dir():
        raise SpecError(f"{option} {out}: {existing} is a file, not a folder")
    try:
        read_only = bool(os.statvfs(existing).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    if read_only:
        raise SpecError(f"{option} {out}: {existing} is on a read-only file system")
    kind = _filesystem(existing)
    if kind in PSEUDO_FILESYSTEMS:
        raise SpecError(f"{option} {out}: {existing} is on the kernel's {kind} file system, where no folder "
                        "can be written; choose a folder on a disk")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise SpecError(f"{option} {out}: no permission to write in {existing}")


def check_new_folder(out: str | Path, option: str = "--out", inputs: tuple[str | Path, ...] = ()) -> Path:
    """Refuse, in one line and before anything is written, an output folder that must not be used by
    a command that never replaces anything (``victims make-dataset``, ``victims train``): one that
    holds files already, one that holds (or is) one of the command's ``inputs``, one inside an input
    folder (a model written into its own ``--test`` set), or one that cannot be written
    (:func:`check_writable_target`). Returns ``out`` resolved."""
    target = Path(out).resolve()
    check_writable_target(target, option)
    for path in (Path(p).resolve() for p in inputs):
        if target == path or target in path.parents:
            raise SpecError(f"{option} {out}: holds this command's input {path}; choose another folder")
        if path.is_dir() and path in target.parents:
            raise SpecError(f"{option} {out}: lies inside this command's input {path}; choose a folder outside it")
    if target.is_dir() and any(target.iterdir()):
        raise SpecError(f"{option} {out}: already holds files; this command writes only into a new or "
                        "empty folder, so nothing in it is replaced; choose another folder")
    return target


@contextlib.contextmanager
def restored_on_failure(folder: str | Path) -> Iterator[None]:
    """For a command that writes into a new or empty ``folder`` (:func:`check_new_folder`): whatever
    ends the block with an exception (Ctrl-C, SIGTERM, a full disk) removes what it wrote, and the
    folder is left as it was found, absent or empty."""
    folder = Path(folder)
    existed = folder.is_dir()
    try:
        yield
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        if existed:
            folder.mkdir(exist_ok=True)
        raise
