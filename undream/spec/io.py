"""Reading spec files (JSON, YAML), writing the canonical ``sequence.json``, checking an output folder.

Errors are one :class:`~undream.errors.SpecError` line naming the file (and
the line of a syntax error), whichever reader finds them.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from undream.errors import SpecError
from undream.spec.model import Sequence


def _text(path: Path) -> str:
    if not path.is_file():
        raise SpecError(f"{path}: file not found")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise SpecError(f"{path}: not a text file (byte 0x{err.object[err.start]:02x} at offset {err.start} "
                        "is not UTF-8)") from None
    except OSError as err:
        raise SpecError(f"{path}: cannot read ({err.strerror})") from None


def read_json(path: str | Path) -> Any:
    """The parsed content of a JSON file."""
    path = Path(path)
    try:
        return json.loads(_text(path))
    except json.JSONDecodeError as err:
        raise SpecError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None


def read_yaml(path: str | Path) -> Any:
    """The parsed content of a YAML file (``yaml.safe_load``)."""
    import yaml

    path = Path(path)
    try:
        return yaml.safe_load(_text(path))
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
    Path(path).write_text(json.dumps(seq.to_json(), indent=1) + "\n")


def resolve_against(path: str | Path, base_dir: Path | None) -> str:
    """``path`` as an absolute path: a relative one against ``base_dir`` (the spec's folder; the
    working directory when None)."""
    p = Path(path)
    return str((p if p.is_absolute() or base_dir is None else Path(base_dir) / p).resolve())


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
    if not os.access(existing, os.W_OK | os.X_OK):
        raise SpecError(f"{option} {out}: no permission to write in {existing}")
