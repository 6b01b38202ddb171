"""Ground and background props (trees, buildings, a city block) for the simulation scene.

Props are placed once per sequence from its seed and dropped wherever they
would come near any camera's line of sight to the object, so they never hide
it: ``park`` and ``street`` on a ring around the object's first position,
``city`` along a road through it (:func:`city_props`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from undream.lru import LRU
from undream.scene.xml import Mat4, UVScale
from undream.spec import Sequence

GROUND_HALF_SIZE = 100.0  # metres
GROUND_COLOURS = {
    "plain": ((0.42, 0.42, 0.40), (0.36, 0.36, 0.35)),
    "park": ((0.16, 0.30, 0.09), (0.20, 0.35, 0.11)),
    "street": ((0.13, 0.13, 0.14), (0.16, 0.16, 0.17)),
    "city": ((0.085, 0.085, 0.09), (0.10, 0.10, 0.105)),  # asphalt
}
CITY_CLEARANCE = 3.0  # metres between a city prop's footprint and any sight line, camera or actor
CITY_HALF_LENGTH = 30.0  # the block's extent along its road, metres either side of the object
ROAD_HALF_WIDTH = 4.0  # metres; pavements beyond it, buildings beyond those
FACADES = ((0.45, 0.45, 0.44), (0.42, 0.24, 0.17), (0.55, 0.50, 0.40), (0.30, 0.34, 0.40))  # concrete, brick,
# sandstone, blue-grey (linear albedo before each tower's random tint)


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


_PLACED: LRU[tuple[int, str], tuple[Sequence, list[Prop]]] = LRU(8)  # (id of a sequence, background) → its props


def props(seq: Sequence, background: str) -> list[Prop]:
    """Seeded props for ``background`` that keep every line of sight to the object clear.

    Placed once per sequence and background (the last few are kept): every frame's scene file asks
    again, and each placement checks every frame's line of sight, so a multi-condition run's init
    of 1,728 frames spent most of its time here placing the same props again (quadratic in frames).
    """
    key = (id(seq), background)
    held = _PLACED.touch(key) if key in _PLACED else None
    if held is None or held[0] is not seq:  # a Sequence is immutable: the same object, the same props
        held = _PLACED.put(key, (seq, _place(seq, background)))
    return list(held[1])


def _place(seq: Sequence, background: str) -> list[Prop]:
    if background == "plain":
        return []
    if background == "city":
        return city_props(seq)
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


# --- city: a road with pavements, street lamps, lane markings and tall buildings -------------------

@dataclass(frozen=True)
class _RoadFrame:
    """The block's frame: ``a`` metres along the road, ``b`` across it, from the object's first position."""

    origin: np.ndarray  # (3,) metres, on the ground
    along: np.ndarray  # (3,) unit, horizontal
    across: np.ndarray  # (3,) unit, horizontal: along × +Y

    def at(self, a: float, y: float, b: float) -> np.ndarray:
        """4×4: the road frame's rotation, translated to (a, y, b)."""
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2] = self.along, (0.0, 1.0, 0.0), self.across
        m[:3, 3] = self.origin + a * self.along + y * np.array([0.0, 1.0, 0.0]) + b * self.across
        return m


def road_frame(seq: Sequence) -> _RoadFrame:
    """The road runs through the object's first position along its travel (first → last frame), else along +X."""
    first = np.array(seq.frames[0].object_to_world.translation)
    travel = np.array(seq.frames[-1].object_to_world.translation) - first
    travel[1] = 0.0
    along = travel / np.linalg.norm(travel) if np.linalg.norm(travel) > 0.5 else np.array([1.0, 0.0, 0.0])
    return _RoadFrame(np.array([first[0], 0.0, first[2]]), along, np.cross(along, [0.0, 1.0, 0.0]))


def _box(road: _RoadFrame, a: float, b: float, size: tuple[float, float, float], y0: float = 0.0) -> np.ndarray:
    """A Mitsuba ``cube`` ([−1, 1]³) as a box of ``size`` (along, up, across; metres) standing at y0."""
    la, h, lb = size
    return road.at(a, y0 + h / 2, b) @ np.diag([la / 2, h / 2, lb / 2, 1.0])


def _building_block(road: _RoadFrame, a: float, b: float, size: tuple[float, float, float],
                    rng: np.random.Generator) -> list[Prop]:
    """A tower of ``size`` (along, height, across) with dark ribbon windows every 3.6 m from 2 m up."""
    base = np.array(FACADES[int(rng.integers(len(FACADES)))])
    tint = tuple(float(x) for x in np.clip(base * rng.uniform(0.8, 1.2) * rng.uniform(0.93, 1.07, 3), 0.0, 0.9))
    out = [Prop("cube", _box(road, a, b, size), tint)]
    glass = (0.04, 0.05, 0.07 + 0.04 * rng.uniform())
    for y in np.arange(2.0, size[1] - 1.5, 3.6):
        out.append(Prop("cube", _box(road, a, b, (size[0] + 0.08, 1.3, size[2] + 0.08), y0=y), glass))
    return out


def _lamp(road: _RoadFrame, a: float, b: float) -> list[Prop]:
    """A 5 m pole (Mitsuba ``cylinder``, axis +Z → +Y) under a pale globe."""
    rot = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    pole = road.at(a, 0.0, b) @ rot @ np.diag([0.07, 0.07, 5.0, 1.0])
    globe = road.at(a, 5.15, b) @ np.diag([0.25, 0.25, 0.25, 1.0])
    return [Prop("cylinder", pole, (0.18, 0.19, 0.2)), Prop("sphere", globe, (0.85, 0.82, 0.7))]


def city_props(seq: Sequence) -> list[Prop]:
    """A seeded city block along a road through the object (:func:`road_frame`).

    Pavements (0.15 m kerbs, 5 m slabs) either side of a 2 × 4 m road with
    dashed centre markings, street lamps every 15 m, and a row of towers
    (8–30 m tall, 7–13 m wide; concrete, brick, sandstone or blue-grey
    façades with dark ribbon windows)
    behind each pavement. A prop whose footprint comes within
    :data:`CITY_CLEARANCE` of a camera's line of sight to the object, a
    camera or an actor's position is dropped (footprints as discs around
    their centres: conservative).
    """
    rng = np.random.default_rng(seq.seed)
    road = road_frame(seq)
    segments, points = _sight_segments(seq), _actor_points(seq)
    out: list[Prop] = []

    def keep(a: float, b: float, half_a: float, half_b: float, props_: list[Prop]) -> None:
        p = road.origin + a * road.along + b * road.across
        if _clear(p, float(np.hypot(half_a, half_b)) + CITY_CLEARANCE, segments, points):
            out.extend(props_)

    for a in np.arange(-CITY_HALF_LENGTH + 3.0, CITY_HALF_LENGTH, 8.0):  # dashed centre line
        keep(a, 0.0, 1.5, 0.08, [Prop("rectangle", road.at(a, 0.004, 0.0) @ _flat(1.5, 0.08), (0.8, 0.8, 0.75))])
    for side in (-1.0, 1.0):
        for a in np.arange(-CITY_HALF_LENGTH + 2.5, CITY_HALF_LENGTH, 5.0):  # kerb and pavement slabs
            keep(a, side * (ROAD_HALF_WIDTH + 2.0), 2.5, 2.0,
                 [Prop("cube", _box(road, a, side * (ROAD_HALF_WIDTH + 2.0), (4.96, 0.15, 4.0)), (0.42, 0.41, 0.39))])
        for a in np.arange(-CITY_HALF_LENGTH + 7.5 * (side > 0), CITY_HALF_LENGTH, 15.0):
            keep(a, side * (ROAD_HALF_WIDTH + 0.6), 0.25, 0.25, _lamp(road, a, side * (ROAD_HALF_WIDTH + 0.6)))
        a = -CITY_HALF_LENGTH
        while a < CITY_HALF_LENGTH:
            width, depth, height = rng.uniform(7, 13), rng.uniform(8, 14), rng.uniform(8, 30)
            b = side * (ROAD_HALF_WIDTH + 4.5 + depth / 2 + rng.uniform(0.0, 2.0))
            block = _building_block(road, a + width / 2, b, (width, height, depth), rng)
            keep(a + width / 2, b, width / 2 + 0.05, depth / 2 + 0.05, block)
            a += width + rng.uniform(1.0, 3.0)
    return out


def _flat(half_a: float, half_b: float) -> np.ndarray:
    """A Mitsuba ``rectangle`` ([−1, 1]² at z = 0, normal +Z) lying on the ground, normal +Y."""
    return np.array([[half_a, 0, 0, 0], [0, 0, 1.0, 0], [0, -half_b, 0, 0], [0, 0, 0, 1.0]])


def _sight_segments(seq: Sequence) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every frame's camera → object segment on the ground (xz)."""
    return [(np.array(f.camera.to_world.translation)[[0, 2]], np.array(f.object_to_world.translation)[[0, 2]])
            for f in seq.frames]


def _actor_points(seq: Sequence) -> list[np.ndarray]:
    return [np.array(a.to_world.translation)[[0, 2]] for f in seq.frames for a in f.actors]


def _clear(p: np.ndarray, radius: float, segments: list[tuple[np.ndarray, np.ndarray]],
           points: list[np.ndarray]) -> bool:
    """True when ground point ``p`` is farther than ``radius`` (xz) from every segment and point."""
    q = p[[0, 2]]
    for a, b in segments + [(x, x) for x in points]:
        ab = b - a
        t = np.clip(np.dot(q - a, ab) / max(np.dot(ab, ab), 1e-12), 0.0, 1.0)
        if np.linalg.norm(a + t * ab - q) < radius:
            return False
    return True
