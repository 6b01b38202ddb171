"""File names inside a scene directory (what ``undream init`` writes and every reader opens).

Frame files carry the frame's *index* (its number in the sequence,
``Frame.index``), zero-padded to :data:`FRAME_DIGITS` digits: ``frames/sim_0007.xml``.
"""
from __future__ import annotations

from pathlib import Path

FRAME_DIGITS = 4
SEQUENCE_FILE = "sequence.json"


def frame_name(kind: str, index: int) -> str:
    """``kind_NNNN`` for frame ``index`` (kind: sim, grad, white, mask, frame)."""
    return f"{kind}_{index:0{FRAME_DIGITS}d}"


def mesh_name(name: str, index: int) -> str:
    """``NAME_NNNN``: the stem of frame ``index``'s file of a per-frame mesh (``meshes/NAME_NNNN.ply``)."""
    return frame_name(name, index)


def frame_xml(scene_dir: str | Path, kind: str, index: int) -> Path:
    """``scene_dir/frames/<kind>_NNNN.xml``: the Mitsuba scene of frame ``index`` (kind sim or grad)."""
    return Path(scene_dir) / "frames" / f"{frame_name(kind, index)}.xml"


def mask_png(scene_dir: str | Path, index: int) -> Path:
    """``scene_dir/verify/mask_NNNN.png``: the object's visible pixels in frame ``index``."""
    return Path(scene_dir) / "verify" / f"{frame_name('mask', index)}.png"
