"""The scene model: frozen, validated dataclasses with a JSON round trip.

Canonical convention (Mitsuba's): right-handed, Y up, metres. A transform is a
4×4 matrix in column-vector form (``p_world = M @ p_local``), stored row-major.
A camera's local frame is Mitsuba's: it looks along +Z with +Y up and +X to
the image's left. Colours and textures are sRGB values in [0, 1].

This module imports nothing heavy (no mitsuba, torch, celery, sqlalchemy).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec import _check as c
from undream.spec.limits import MAX_FRAMES

Row = tuple[float, float, float, float]
Matrix = tuple[Row, Row, Row, Row]

WEATHERS = ("clear", "cloudy", "night", "fog", "rain", "snow")
NIGHT_LAMP_OFFSET = (2.5, 6.0, 2.5)  # metres from the object: up and to one side
NIGHT_LAMP_INTENSITY = (30.0, 25.0, 18.0)  # warm white
BACKGROUNDS = ("plain", "park", "street", "city")
ENVMAP_SUFFIXES = (".exr", ".hdr")
BUILTIN_PREFIX = "builtin:"


def _matmul3(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def _det3(m: list[list[float]]) -> float:
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


@dataclass(frozen=True)
class Transform:
    """An affine 4×4 transform, column-vector convention, rows stored in order."""

    matrix: Matrix

    def __post_init__(self) -> None:
        rows = self.matrix
        if isinstance(rows, (str, bytes)) or not hasattr(rows, "__len__") or len(rows) != 4:
            raise c.fail("matrix", rows, "must be 4 rows of 4 numbers")
        m = tuple(c.vector(f"matrix[{i}]", r, 4) for i, r in enumerate(rows))
        if m[3] != (0.0, 0.0, 0.0, 1.0):
            raise c.fail("matrix[3]", list(m[3]), "must be [0, 0, 0, 1] (affine transform)")
        if abs(_det3([list(r[:3]) for r in m[:3]])) < 1e-12:
            raise c.fail("matrix", [list(r) for r in m], "must have an invertible 3×3 part")
        object.__setattr__(self, "matrix", m)

    @classmethod
    def identity(cls) -> "Transform":
        return cls(((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1)))

    @classmethod
    def from_rows(cls, rows: Any) -> "Transform":
        """From any nested 4×4 sequence (lists, tuples, numpy arrays)."""
        return cls(tuple(tuple(float(v) for v in r) for r in rows))  # type: ignore[arg-type]

    @property
    def translation(self) -> tuple[float, float, float]:
        return (self.matrix[0][3], self.matrix[1][3], self.matrix[2][3])

    @property
    def linear(self) -> list[list[float]]:
        return [list(r[:3]) for r in self.matrix[:3]]

    def is_rigid(self, tol: float = 1e-6) -> bool:
        """True when the 3×3 part is a rotation (orthonormal, determinant +1)."""
        r = self.linear
        rtr = _matmul3([list(col) for col in zip(*r)], r)
        ortho = all(abs(rtr[i][j] - (i == j)) < tol for i in range(3) for j in range(3))
        return ortho and abs(_det3(r) - 1.0) < tol

    def to_json(self) -> list[list[float]]:
        return [list(r) for r in self.matrix]


@dataclass(frozen=True)
class TextureParam:
    """The adversarial texture: sRGB in [0, 1], repeated ``uv_scale`` times.

    ``resolution`` is (width, height) in texels, the order of
    :attr:`Camera.resolution` and of image files; the texture array is
    ``height×width×3`` (:attr:`shape`).
    """

    name: str = "adv_texture"
    resolution: tuple[int, int] = (256, 256)  # (width, height) in texels
    uv_scale: tuple[float, float] = (1.0, 1.0)  # repeats along u and v
    init: Any = (0.5, 0.5, 0.5)  # an sRGB colour, or the path of an image file

    def __post_init__(self) -> None:
        c.name("name", self.name)
        object.__setattr__(self, "resolution", c.ints("resolution", self.resolution, 2, 1, 8192))
        uv = c.vector("uv_scale", self.uv_scale, 2)
        for i, v in enumerate(uv):
            c.positive(f"uv_scale[{i}]", v)
        object.__setattr__(self, "uv_scale", uv)
        if isinstance(self.init, str):
            if not self.init:
                raise c.fail("init", self.init, "must be an sRGB colour or an image path")
        else:
            object.__setattr__(self, "init", c.color("init", self.init))

    @property
    def shape(self) -> tuple[int, int, int]:
        """The texture array's shape: (height, width, 3)."""
        return (self.resolution[1], self.resolution[0], 3)

    def to_json(self) -> dict[str, Any]:
        init = self.init if isinstance(self.init, str) else list(self.init)
        return {"name": self.name, "resolution": list(self.resolution),
                "uv_scale": list(self.uv_scale), "init": init}

    @classmethod
    def from_json(cls, d: Any) -> "TextureParam":
        d = c.mapping("texture", d)
        c.no_extra(d, {"name", "resolution", "uv_scale", "init"})
        kw = dict(d)
        if isinstance(kw.get("uv_scale"), (int, float)) and not isinstance(kw.get("uv_scale"), bool):
            kw["uv_scale"] = (kw["uv_scale"], kw["uv_scale"])
        return cls(**kw)


@dataclass(frozen=True)
class Asset:
    """A UV-mapped mesh: ``builtin:NAME`` or the path of an OBJ/PLY file.

    Mesh coordinates are canonical (Y up) metres, multiplied by ``scale``.
    ``texture`` is set for the adversarial object; other actors use ``color``.
    An animated mesh is one file per frame: a path with a ``{frame}`` field
    (Python format syntax, e.g. ``walk_{frame:04d}.ply``) that the frame's
    *index* fills (:meth:`mesh_at`); the adversarial object's files must
    then share one UV layout (checked by ``undream init``).
    """

    name: str
    mesh: str
    scale: float = 1.0
    texture: TextureParam | None = None
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)

    def __post_init__(self) -> None:
        c.name("name", self.name)
        if not isinstance(self.mesh, str) or not self.mesh:
            raise c.fail("mesh", self.mesh, "must be 'builtin:NAME' or a path to an .obj or .ply file")
        if not self.mesh.startswith(BUILTIN_PREFIX) and not self.mesh.lower().endswith((".obj", ".ply")):
            raise c.fail("mesh", self.mesh, "must be 'builtin:NAME' or a path to an .obj or .ply file")
        if self.per_frame:
            if self.builtin is not None:
                raise c.fail("mesh", self.mesh, "a builtin mesh has no per-frame files ('{frame}')")
            try:
                self.mesh_at(0)
            except (KeyError, IndexError, ValueError, AttributeError):
                raise c.fail("mesh", self.mesh, "must be a path whose only field is {frame}, "
                             "e.g. 'walk_{frame:04d}.ply'") from None
        object.__setattr__(self, "scale", c.positive("scale", self.scale))
        object.__setattr__(self, "color", c.color("color", self.color))
        if self.texture is not None and not isinstance(self.texture, TextureParam):
            raise c.fail("texture", self.texture, "must be a TextureParam")

    @property
    def builtin(self) -> str | None:
        return self.mesh[len(BUILTIN_PREFIX):] if self.mesh.startswith(BUILTIN_PREFIX) else None

    @property
    def per_frame(self) -> bool:
        """True when the mesh is one file per frame (a ``{frame}`` field in :attr:`mesh`)."""
        return "{" in self.mesh

    def mesh_at(self, index: int) -> str:
        """The mesh of frame ``index``: :attr:`mesh` with ``{frame}`` filled in (the path itself if static)."""
        return self.mesh.format(frame=index) if self.per_frame else self.mesh

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "mesh": self.mesh, "scale": self.scale,
                             "color": list(self.color)}
        if self.texture is not None:
            d["texture"] = self.texture.to_json()
        return d

    @classmethod
    def from_json(cls, d: Any) -> "Asset":
        d = c.mapping("asset", d)
        c.no_extra(d, {"name", "mesh", "scale", "texture", "color"})
        kw = dict(d)
        c.require(kw, "name")
        c.require(kw, "mesh")
        if kw.get("texture") is not None:
            with c.at("texture"):
                kw["texture"] = TextureParam.from_json(kw["texture"])
        return cls(**kw)


@dataclass(frozen=True)
class Environment:
    """Sun and sky, weather and background of one frame.

    ``time_of_day`` in hours [0, 24) places the sun (see
    :func:`sun_direction`); ``fog_density`` is the extinction in 1/m used when
    the weather is ``fog`` (``rain`` and ``snow`` bring their own, lighter
    haze: :mod:`undream.scene.environment`).

    ``envmap``: the path of an equirectangular HDR map (``.exr`` or ``.hdr``,
    width = 2 × height, linear radiance; row 0 is straight up; the left edge
    looks along −Z, a quarter of the width in along +X, the centre along +Z) that
    replaces the procedural sky *and* the sun (the map carries its light);
    the weather keeps its medium, its ground and, at night, its lamp.
    ``envmap_scale`` multiplies the map's radiance; ``envmap_rotation_deg``
    turns it about +Y (right-handed: +X towards −Z). In a scene directory
    the path is relative to the directory (``textures/envmap.exr``).

    ``lamp_offset`` (metres from the object's origin) and ``lamp_intensity``
    (linear RGB, W/sr in undream's units) place and colour the night's point
    lamp; the defaults are the one lamp every night had before these fields.
    Other weathers have no lamp and refuse them.
    """

    weather: str = "clear"
    time_of_day: float = 14.0
    background: str = "plain"
    sun_max_elevation_deg: float = 60.0
    fog_density: float = 0.08
    envmap: str | None = None
    envmap_scale: float = 1.0
    envmap_rotation_deg: float = 0.0
    lamp_offset: tuple[float, float, float] = NIGHT_LAMP_OFFSET
    lamp_intensity: tuple[float, float, float] = NIGHT_LAMP_INTENSITY

    def __post_init__(self) -> None:
        c.choice("weather", self.weather, WEATHERS)
        object.__setattr__(self, "lamp_offset", c.point("lamp_offset", self.lamp_offset))
        rgb = c.vector("lamp_intensity", self.lamp_intensity, 3)
        if any(x < 0 for x in rgb) or not any(rgb):
            raise c.fail("lamp_intensity", self.lamp_intensity, "must be three numbers >= 0, not all 0")
        object.__setattr__(self, "lamp_intensity", rgb)
        for name, value, default in (("lamp_offset", self.lamp_offset, NIGHT_LAMP_OFFSET),
                                     ("lamp_intensity", rgb, NIGHT_LAMP_INTENSITY)):
            if self.weather != "night" and value != default:
                raise c.fail(name, list(value), f"a lamp lights the night only; weather is {self.weather!r}")
        c.choice("background", self.background, BACKGROUNDS)
        if self.envmap is not None and (not isinstance(self.envmap, str)
                                        or not self.envmap.lower().endswith(ENVMAP_SUFFIXES)):
            raise c.fail("envmap", self.envmap, "must be the path of an .exr or .hdr equirectangular map")
        object.__setattr__(self, "envmap_scale", c.positive("envmap_scale", self.envmap_scale))
        object.__setattr__(self, "envmap_rotation_deg", c.finite("envmap_rotation_deg", self.envmap_rotation_deg))
        t = c.finite("time_of_day", self.time_of_day)
        if not 0 <= t < 24:
            raise c.fail("time_of_day", self.time_of_day, "must be hours in [0, 24)")
        object.__setattr__(self, "time_of_day", t)
        e = c.finite("sun_max_elevation_deg", self.sun_max_elevation_deg)
        if not 0 < e <= 90:
            raise c.fail("sun_max_elevation_deg", e, "must be in (0, 90]")
        object.__setattr__(self, "sun_max_elevation_deg", e)
        object.__setattr__(self, "fog_density", c.positive("fog_density", self.fog_density))

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"weather": self.weather, "time_of_day": self.time_of_day,
                             "background": self.background,
                             "sun_max_elevation_deg": self.sun_max_elevation_deg,
                             "fog_density": self.fog_density}
        if self.envmap is not None:  # absent otherwise: sequences without a map keep their files
            d.update(envmap=self.envmap, envmap_scale=self.envmap_scale,
                     envmap_rotation_deg=self.envmap_rotation_deg)
        if not self.default_lamp:  # likewise: the default lamp's scenes keep their files
            d.update(lamp_offset=list(self.lamp_offset), lamp_intensity=list(self.lamp_intensity))
        return d

    @property
    def default_lamp(self) -> bool:
        """Whether the night lamp is the one every night had before it could be moved."""
        return self.lamp_offset == NIGHT_LAMP_OFFSET and self.lamp_intensity == NIGHT_LAMP_INTENSITY

    @classmethod
    def from_json(cls, d: Any) -> "Environment":
        d = c.mapping("environment", d)
        c.no_extra(d, set(cls.__dataclass_fields__))
        return cls(**d)


def sun_direction(env: Environment) -> tuple[tuple[float, float, float], float]:
    """Unit vector pointing *towards* the sun and its elevation in degrees.

    A simple day model: the sun rises in the east (+X) at 6 h, culminates in
    the south (-Z) at 12 h at ``sun_max_elevation_deg`` and sets in the west
    (-X) at 18 h; between 18 h and 6 h its elevation is negative.
    """
    phase = math.pi * (env.time_of_day - 6.0) / 12.0  # 0 at sunrise, pi at sunset
    elev = math.radians(env.sun_max_elevation_deg) * math.sin(phase)
    horiz = (math.cos(phase), -math.sin(phase))  # (x, z): east at sunrise, south at noon
    d = (math.cos(elev) * horiz[0], math.sin(elev), math.cos(elev) * horiz[1])
    return d, math.degrees(elev)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    ``to_world`` must be rigid (a rotation and a translation, metres).
    ``fov_deg`` is the horizontal field of view of the film, whose size is
    ``film`` (width, height) in pixels or, if unset, ``resolution``. The image
    is the centred ``resolution`` window of the film (a centre crop).
    """

    to_world: Transform
    fov_deg: float
    resolution: tuple[int, int]  # (width, height) in pixels
    film: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.to_world, Transform):
            raise c.fail("to_world", self.to_world, "must be a Transform")
        if not self.to_world.is_rigid(1e-5):
            raise c.fail("to_world", self.to_world.to_json(),
                         "must be rigid (orthonormal rotation with determinant +1, no scale)")
        fov = c.finite("fov_deg", self.fov_deg)
        if not 0 < fov < 180:
            raise c.fail("fov_deg", fov, "must be in (0, 180) degrees")
        object.__setattr__(self, "fov_deg", fov)
        res = c.ints("resolution", self.resolution, 2, 1, 16384)
        object.__setattr__(self, "resolution", res)
        if self.film is not None:
            film = c.ints("film", self.film, 2, 1, 16384)
            if film[0] < res[0] or film[1] < res[1]:
                raise c.fail("film", list(film), f"must be at least the resolution {list(res)}")
            object.__setattr__(self, "film", film)

    @property
    def film_size(self) -> tuple[int, int]:
        return self.film or self.resolution

    @property
    def crop_offset(self) -> tuple[int, int]:
        fw, fh = self.film_size
        return ((fw - self.resolution[0]) // 2, (fh - self.resolution[1]) // 2)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"to_world": self.to_world.to_json(), "fov_deg": self.fov_deg,
                             "resolution": list(self.resolution)}
        if self.film is not None:
            d["film"] = list(self.film)
        return d

    @classmethod
    def from_json(cls, d: Any) -> "Camera":
        d = c.mapping("camera", d)
        c.no_extra(d, {"to_world", "fov_deg", "resolution", "film"})
        kw = dict(d)
        for k in ("to_world", "fov_deg", "resolution"):
            c.require(kw, k)
        with c.at("to_world"):
            kw["to_world"] = Transform(kw["to_world"])
        return cls(**kw)


@dataclass(frozen=True)
class ActorPose:
    """Where one extra actor (named in :attr:`Sequence.actors`) is in a frame."""

    name: str
    to_world: Transform

    def __post_init__(self) -> None:
        c.name("name", self.name)
        if not isinstance(self.to_world, Transform):
            raise c.fail("to_world", self.to_world, "must be a Transform")

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "to_world": self.to_world.to_json()}

    @classmethod
    def from_json(cls, d: Any) -> "ActorPose":
        d = c.mapping("actor", d)
        c.no_extra(d, {"name", "to_world"})
        with c.at("to_world"):
            m = Transform(c.require(d, "to_world"))
        return cls(name=c.require(d, "name"), to_world=m)


@dataclass(frozen=True)
class Frame:
    """One frame: camera, the adversarial object's pose, actors, environment."""

    index: int
    camera: Camera
    object_to_world: Transform
    environment: Environment = field(default_factory=Environment)
    actors: tuple[ActorPose, ...] = ()
    time: float = 0.0  # seconds since the sequence's start

    def __post_init__(self) -> None:
        c.integer("index", self.index, 0, 10**7)
        object.__setattr__(self, "time", c.finite("time", self.time))
        if not isinstance(self.camera, Camera):
            raise c.fail("camera", self.camera, "must be a Camera")
        if not isinstance(self.object_to_world, Transform):
            raise c.fail("object_to_world", self.object_to_world, "must be a Transform")
        object.__setattr__(self, "actors", tuple(self.actors))
        names = [a.name for a in self.actors]
        if len(set(names)) != len(names):
            raise c.fail("actors", names, "must name each actor once")

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "time": self.time, "camera": self.camera.to_json(),
                "object_to_world": self.object_to_world.to_json(),
                "environment": self.environment.to_json(),
                "actors": [a.to_json() for a in self.actors]}

    @classmethod
    def from_json(cls, d: Any) -> "Frame":
        d = c.mapping("frame", d)
        c.no_extra(d, {"index", "time", "camera", "object_to_world", "environment", "actors"})
        kw = dict(d)
        for k in ("index", "camera", "object_to_world"):
            c.require(kw, k)
        with c.at("camera"):
            kw["camera"] = Camera.from_json(kw["camera"])
        with c.at("object_to_world"):
            kw["object_to_world"] = Transform(kw["object_to_world"])
        if "environment" in kw:
            with c.at("environment"):
                kw["environment"] = Environment.from_json(kw["environment"])
        kw["actors"] = tuple(_each("actors", kw.get("actors", []), ActorPose.from_json))
        return cls(**kw)


SEQUENCE_VERSION = 1


@dataclass(frozen=True)
class Condition:
    """One condition of a multi-condition sequence: ``frames`` consecutive frames that were one
    scene of their own."""

    name: str
    frames: int

    def __post_init__(self) -> None:
        c.name("name", self.name)
        c.integer("frames", self.frames, 1, MAX_FRAMES)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "frames": self.frames}

    @classmethod
    def from_json(cls, d: Any) -> "Condition":
        d = c.mapping("condition", d)
        c.no_extra(d, {"name", "frames"})
        c.require(d, "name")
        c.require(d, "frames")
        return cls(**d)


@dataclass(frozen=True)
class Sequence:
    """Ordered frames of one adversarial object among extra actors.

    ``conditions``: empty for one scene; for a multi-condition sequence (several scenes of one
    object, :mod:`undream.scenedir.conditions`) the scenes in frame order, their frame counts
    summing to the frames'. Background props are placed once for the whole sequence (clear of
    every frame's line of sight): one place seen under every condition.
    """

    name: str
    asset: Asset
    frames: tuple[Frame, ...]
    actors: tuple[Asset, ...] = ()
    fps: float = 10.0
    source: str = "json"
    seed: int = 0
    conditions: tuple[Condition, ...] = ()

    def __post_init__(self) -> None:
        c.name("name", self.name)
        if not isinstance(self.asset, Asset):
            raise c.fail("asset", self.asset, "must be an Asset")
        if self.asset.texture is None:
            raise SpecError("asset.texture: the adversarial asset needs a texture parameter")
        object.__setattr__(self, "fps", c.positive("fps", self.fps))
        c.integer("seed", self.seed, 0, 2**32 - 1)
        frames = tuple(self.frames)
        if not frames:
            raise c.fail("frames", [], "must hold at least one frame")
        if len(frames) > MAX_FRAMES:
            raise _too_many_frames(len(frames))
        idx = [f.index for f in frames]
        if idx != sorted(set(idx)):
            raise c.fail("frames", idx, "must have strictly increasing indices")
        object.__setattr__(self, "frames", frames)
        object.__setattr__(self, "actors", tuple(self.actors))
        names = {a.name for a in self.actors}
        if len(names) != len(self.actors) or self.asset.name in names:
            raise c.fail("actors", [a.name for a in self.actors],
                         "must have unique names, different from the adversarial asset's")
        for f in frames:
            for a in f.actors:
                if a.name not in names:
                    raise SpecError(f"frames[{f.index}].actors: unknown actor {a.name!r} "
                                    f"(declared: {', '.join(sorted(names)) or 'none'})")
        object.__setattr__(self, "conditions", tuple(self.conditions))
        if self.conditions:
            counted = sum(k.frames for k in self.conditions)
            if counted != len(frames):
                raise c.fail("conditions", [k.name for k in self.conditions],
                             f"must hold the {len(frames)} frames between them (they hold {counted})")
            cnames = [k.name for k in self.conditions]
            if len(set(cnames)) != len(cnames):
                raise c.fail("conditions", cnames, "must have unique names")

    def condition_ranges(self) -> list[tuple[Condition, range]]:
        """Each condition and its frame positions (one, named as the sequence, for a sequence of
        one scene)."""
        parts = self.conditions or (Condition(self.name, len(self.frames)),)
        out, first = [], 0
        for part in parts:
            out.append((part, range(first, first + part.frames)))
            first += part.frames
        return out

    @property
    def texture(self) -> TextureParam:
        assert self.asset.texture is not None  # checked in __post_init__
        return self.asset.texture

    def to_json(self) -> dict[str, Any]:
        return {"version": SEQUENCE_VERSION, "name": self.name, "fps": self.fps,
                "source": self.source, "seed": self.seed, "asset": self.asset.to_json(),
                "actors": [a.to_json() for a in self.actors],
                "frames": [f.to_json() for f in self.frames],
                **({"conditions": [k.to_json() for k in self.conditions]} if self.conditions else {})}

    @classmethod
    def from_json(cls, d: Any) -> "Sequence":
        d = c.mapping("sequence", d)
        c.no_extra(d, {"version", "name", "fps", "source", "seed", "asset", "actors", "frames", "conditions"})
        kw = dict(d)
        version = kw.pop("version", SEQUENCE_VERSION)
        if version != SEQUENCE_VERSION:
            raise c.fail("version", version, f"must be {SEQUENCE_VERSION}")
        for k in ("name", "asset", "frames"):
            c.require(kw, k)
        with c.at("asset"):
            kw["asset"] = Asset.from_json(kw["asset"])
        kw["actors"] = tuple(_each("actors", kw.get("actors", []), Asset.from_json))
        if isinstance(kw["frames"], (list, tuple)) and len(kw["frames"]) > MAX_FRAMES:
            # refused before 10,000 frames are parsed one by one
            raise _too_many_frames(len(kw["frames"]))
        kw["frames"] = tuple(_each("frames", kw["frames"], Frame.from_json))
        kw["conditions"] = tuple(_each("conditions", kw.get("conditions", []), Condition.from_json))
        return cls(**kw)


def _too_many_frames(n: int) -> SpecError:
    return SpecError(f"frames: {n} frames is out of range (valid: 1 ≤ frames ≤ {MAX_FRAMES})")


def _each(prefix: str, items: Any, parse: Any) -> list[Any]:
    if not isinstance(items, (list, tuple)):
        raise c.fail(prefix, items, "must be a list")
    out = []
    for i, item in enumerate(items):
        with c.at(f"{prefix}[{i}]"):
            out.append(parse(item))
    return out
