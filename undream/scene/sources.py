"""Read a sequence from any of its three sources, chosen by the file's content.

- ``*.yaml`` / ``*.yml``: a native trajectory spec (:mod:`undream.scene.trajectory`);
- ``*.json`` with ``"format": "undream-unreal-export"``: an Unreal Engine export
  (:mod:`undream.bridge.unreal_import`);
- any other ``*.json``: the canonical ``sequence.json``.
"""
from __future__ import annotations

from pathlib import Path

from undream.errors import SpecError, UndreamError
from undream.spec import Sequence, load_sequence
from undream.spec.io import read_json, read_yaml

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
    data = read_json(path)
    if isinstance(data, dict) and data.get("format") == UNREAL_FORMAT:
        from undream.bridge.unreal_import import sequence_from_unreal
        return sequence_from_unreal(path)
    return load_sequence(path)


def _from_yaml(path: Path) -> Sequence:
    from undream.scene.trajectory import sequence_from_trajectory

    data = read_yaml(path)
    try:
        return sequence_from_trajectory(data, base_dir=path.parent)
    except UndreamError as err:
        raise type(err)(f"{path}: {err}") from None
