"""Read a sequence from any of its three sources, chosen by the file's content.

- ``*.yaml`` / ``*.yml``: a native trajectory spec (:mod:`undream.scene.trajectory`);
- ``*.json`` with ``"format": "undream-unreal-export"``: an Unreal Engine export
  (:mod:`undream.bridge.unreal_import`);
- any other ``*.json``: the canonical ``sequence.json``.
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml

from undream.errors import SpecError, UndreamError
from undream.spec import Sequence, load_sequence

UNREAL_FORMAT = "undream-unreal-export"


def sequence_from_file(path: str | Path) -> Sequence:
    """Parse a trajectory YAML, an Unreal export or a canonical sequence.json."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return _from_yaml(path)
    if suffix != ".json":
        raise SpecError(f"{path}: unknown spec type {suffix!r} (valid: .yaml, .yml, .json)")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise SpecError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    if isinstance(data, dict) and data.get("format") == UNREAL_FORMAT:
        from undream.bridge.unreal_import import sequence_from_unreal
        return sequence_from_unreal(path)
    return load_sequence(path)


def _from_yaml(path: Path) -> Sequence:
    from undream.scene.trajectory import sequence_from_trajectory

    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise SpecError(f"{path}: not valid YAML{line}") from None
    try:
        return sequence_from_trajectory(data, base_dir=path.parent)
    except UndreamError as err:
        raise type(err)(f"{path}: {err}") from None
