"""A user's environment maps for ``undream init``: checked, then copied into the scene directory.

A sequence's frames name their map in ``environment.envmap`` (a path; relative
ones resolve against the spec's folder). :func:`load_envmaps` reads each
distinct map once with Mitsuba's ``Bitmap`` (``.exr`` or ``.hdr``) and checks
it: readable, equirectangular (width = 2 × height), finite and non-negative.
The scene directory holds every map as ``textures/envmap.exr`` (then
``envmap_1.exr``, ... in order of first use): linear float32 RGB, whatever
the source's format. Its ``sequence.json`` names those files (paths relative
to the directory), and ``metadata.json`` where each came from.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from undream.errors import AssetError
from undream.spec import Sequence
from undream.spec.io import naming, resolve_against
from undream.variant import mitsuba

ENVMAP_DIR = "textures"


@dataclass(frozen=True)
class Envmap:
    """One map as the scene directory will hold it."""

    file: str  # relative to the scene directory: textures/envmap.exr
    source: str  # the absolute path it was read from
    data: np.ndarray  # H×W×3 float32, linear radiance, row 0 straight up


def envmap_file(k: int) -> str:
    """The scene directory's name for the ``k``-th distinct map (0-based)."""
    return f"{ENVMAP_DIR}/envmap.exr" if k == 0 else f"{ENVMAP_DIR}/envmap_{k}.exr"


def load_envmaps(seq: Sequence, base_dir: Path | None) -> tuple[Sequence, list[Envmap]]:
    """The sequence with every ``envmap`` renamed to its file in the scene directory, and the maps.

    Raises :class:`AssetError` (one line naming the field and the file) for a
    missing or unreadable map, one that is not 2:1, or one holding NaN,
    infinite or negative values.
    """
    maps: dict[str, Envmap] = {}
    frames = []
    one_env = len({f.environment for f in seq.frames}) == 1
    for i, f in enumerate(seq.frames):
        env = f.environment
        if env.envmap is not None:
            source = resolve_against(env.envmap, base_dir)
            if source not in maps:
                field = "environment.envmap" if one_env else f"environment[{i}].envmap"
                maps[source] = Envmap(envmap_file(len(maps)), source, read_envmap(source, field))
            env = dataclasses.replace(env, envmap=maps[source].file)
            f = dataclasses.replace(f, environment=env)
        frames.append(f)
    if not maps:
        return seq, []
    return dataclasses.replace(seq, frames=tuple(frames)), list(maps.values())


def read_envmap(path: str | Path, field: str = "environment.envmap") -> np.ndarray:
    """An equirectangular map as H×W×3 float32 linear radiance, checked (see :func:`load_envmaps`)."""
    mi = mitsuba()
    p = Path(path)
    if not p.is_file():
        raise AssetError(f"{field}: {p}: environment map not found")
    try:
        bmp = mi.Bitmap(str(p)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
        data = np.array(bmp, dtype=np.float32).reshape(bmp.height(), bmp.width(), 3)
    except Exception as err:  # Mitsuba raises plain RuntimeError on a file it cannot decode
        last = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise AssetError(f"{field}: {p}: not a readable .exr/.hdr image ({last})") from None
    h, w, _ = data.shape
    if w != 2 * h:
        raise AssetError(f"{field}: {p}: an equirectangular map must be twice as wide as high, got {w}×{h} "
                         f"(width×height)")
    bad = ~np.isfinite(data)
    if bad.any():
        raise AssetError(f"{field}: {p}: {int(bad.any(axis=2).sum())} pixels hold NaN or infinite values")
    if (data < 0).any():
        raise AssetError(f"{field}: {p}: {int((data < 0).any(axis=2).sum())} pixels hold negative radiance "
                         f"(min {float(data.min()):.4g})")
    return data


def write_envmaps(maps: list[Envmap], root: Path) -> None:
    """Write each map into the scene directory ``root`` (linear float32 RGB OpenEXR)."""
    mi = mitsuba()
    for m in maps:
        with naming(root / m.file):
            mi.Bitmap(m.data).write(str(root / m.file))


def envmap_sources(maps: list[Envmap]) -> dict[str, str]:
    """For ``metadata.json``: each map's file in the scene directory → the absolute path it came from."""
    return {m.file: m.source for m in maps}
