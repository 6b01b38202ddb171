"""Ground and background props (trees, buildings) for the simulation scene.

Props are placed once per sequence from its seed, on a ring around the
object's first position, and dropped wherever they would come near any
camera's line of sight to the object, so they never hide it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from undream.scene.xml import Mat4, UVScale
from undream.spec import Sequence

GROUND_HALF_SIZE = 100.0  # metres
GROUND_COLOURS = {
    "plain": ((0.42, 0.42, 0.40), (0.36, 0.36, 0.35)),
    "park": ((0.16, 0.30, 0.09), (0.20, 0.35, 0.11)),
    "street": ((0.13, 0.13, 0.14), (0.16, 0.16, 0.17)),
}


@dataclass(frozen=True)
class Prop:
    """One background primitive: a Mitsuba ``sphere``, ``cylinder`` or ``cube``."""

    shape: str
    to_world: np.ndarray  # 4×4, metres
    colour: tuple[float, float, float]  # sRGB-ish albedo, used as linear reflectance


def ground(background: str, tint: Any = None) -> dict[str, Any]:
    """A 200 m square at y = 0, normal +Y, with a 2 m checkerboard.

    ``tint``: a function of the two check colours giving the ones to use
    (the weather's: :func:`undream.scene.environment.ground_tint`).
    """
    c0, c1 = GROUND_COLOURS[background] if tint is None else tint(GROUND_COLOURS[background])
    s = GROUND_HALF_SIZE
    m = np.array([[s, 0, 0, 0], [0, 0, s, 0], [0, -s, 0, 0], [0, 0, 0, 1.0]])
    tex = {"type": "checkerboard", "color0": {"type": "rgb", "value": list(c0)},
           "color1": {"type": "rgb", "value": list(c1)}, "to_uv": UVScale(s, s)}
    return {"type": "rectangle", "to_world": Mat4.of(m), "bsdf": {"type": "diffuse", "reflectance": tex}}


def _tree(x: float, z: float, rng: np.random.Generator) -> list[Prop]:
    h = rng.uniform(2.5, 4.0)
    trunk = np.diag([0.15, 0.15, h * 0.6, 1.0])
    rot = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])  # cylinder axis +Z → +Y
    trunk = _at(x, 0.0, z) @ rot @ trunk
    r = rng.uniform(0.9, 1.5)
    crown = _at(x, h * 0.6 + r * 0.7, z) @ np.diag([r, r, r, 1.0])
    green = (0.10, rng.uniform(0.22, 0.32), 0.07)
    return [Prop("cylinder", trunk, (0.25, 0.17, 0.10)), Prop("sphere", crown, green)]


def _building(x: float, z: float, rng: np.random.Generator) -> list[Prop]:
    w, d, h = rng.uniform(3, 6), rng.uniform(3, 6), rng.uniform(4, 10)
    m = _at(x, h / 2, z) @ np.diag([w / 2, h / 2, d / 2, 1.0])  # cube spans [-1, 1]
    g = rng.uniform(0.35, 0.6)
    return [Prop("cube", m, (g, g * 0.95, g * 0.9))]


def _at(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def props(seq: Sequence, background: str) -> list[Prop]:
    """Seeded props for ``background`` that keep every line of sight to the object clear."""
    if background == "plain":
        return []
    rng = np.random.default_rng(seq.seed)
    centre = np.array(seq.frames[0].object_to_world.translation)
    make = _tree if background == "park" else _building
    out: list[Prop] = []
    for k in range(14):
        ang = 2 * np.pi * (k + rng.uniform(0.0, 0.6)) / 14
        dist = rng.uniform(12.0, 22.0)
        x, z = centre[0] + dist * np.sin(ang), centre[2] + dist * np.cos(ang)
        if _clear_of_sightlines(seq, np.array([x, 0.0, z]), radius=4.5):
            out += make(x, z, rng)
    return out


def _clear_of_sightlines(seq: Sequence, p: np.ndarray, radius: float) -> bool:
    """True when ``p`` (ground point) is farther than ``radius`` from every camera→object segment in xz."""
    for f in seq.frames:
        a = np.array(f.camera.to_world.translation)[[0, 2]]
        b = np.array(f.object_to_world.translation)[[0, 2]]
        q = p[[0, 2]]
        ab = b - a
        t = np.clip(np.dot(q - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
        if np.linalg.norm(a + t * ab - q) < radius or np.linalg.norm(q - a) < radius:
            return False
    return True
