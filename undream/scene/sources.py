"""Read a sequence from any of its sources, chosen by the file's content.

- ``*.yaml`` / ``*.yml``: a native trajectory spec (:mod:`undream.scene.trajectory`);
- ``*.json`` with ``"format": "undream-unreal-export"``: an Unreal Engine export
  (:mod:`undream.bridge.unreal_import`);
- any other ``*.json``: the canonical ``sequence.json``;
- ``*.blend``: a Blender scene, given as a :class:`~undream.bridge.blender_import.BlendSource`
  (the file and the object's name; :mod:`undream.bridge.blender_import`).
"""
from __future__ import annotations

from pathlib import Path

from undream.bridge.blender_import import BlendSource, sequence_from_blend
from undream.bridge.unreal_import import sequence_from_unreal
from undream.errors import SpecError, UndreamError
from undream.spec import Sequence, load_sequence
from undream.spec.io import read_json, read_yaml

UNREAL_FORMAT = "undream-unreal-export"


def sequence_from_file(path: "str | Path | BlendSource", cache_dir: str | Path | None = None) -> Sequence:
    """Parse a trajectory YAML, an Unreal export, a canonical sequence.json or a :class:`BlendSource`
    (``cache_dir``: undream's cache folder, for a YAML's ``asset:NAME``s)."""
    if isinstance(path, BlendSource):
        return sequence_from_blend(path)
    path = Path(path)
    if not path.is_file():
        raise SpecError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix == ".blend":
        raise SpecError(f"{path}: a .blend file needs the name of the adversarial object "
                        "(undream init FILE.blend --object NAME)")
    if suffix in (".yaml", ".yml"):
        return _from_yaml(path, cache_dir)
    if suffix != ".json":
        raise SpecError(f"{path}: unknown spec type {suffix!r} (valid: .yaml, .yml, .json, .blend)")
    data = read_json(path)
    if isinstance(data, dict) and data.get("format") == UNREAL_FORMAT:
        return sequence_from_unreal(path)
    return load_sequence(path)


def _from_yaml(path: Path, cache_dir: str | Path | None) -> Sequence:
    from undream.scene.trajectory import sequence_from_trajectory

    data = read_yaml(path)
    try:
        return sequence_from_trajectory(data, base_dir=path.parent, cache_dir=cache_dir)
    except UndreamError as err:
        raise type(err)(f"{path}: {err}") from None
