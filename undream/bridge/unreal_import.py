"""Import an Unreal Engine sequence export into a canonical :class:`~undream.spec.Sequence`.

``deploy/unreal/export_sequence.py`` (run in Unreal's editor Python) writes
the export; ``docs/unreal.md`` describes it for users. The format, version 1::

    {"format": "undream-unreal-export", "version": 1,
     "sequence": "/Game/Seq/DriveBy",         # optional; gives the name
     "name": "drive_by",                       # optional; overrides it
     "fps": 30,                                # display rate, frames/second
     "camera": {"name": "CineCam"},            # optional, informative
     "object": {"actor": "AdvBin", "asset": ASSET},     # the adversarial object
     "actors": [{"actor": "Car1", "asset": ASSET}],     # optional extra actors
     "environment": ENVIRONMENT,               # optional, all frames
     "frames": [FRAME, ...]}

    FRAME = {"frame": 12,                      # integer >= 0, or digits "0012"
             "time": 0.4,                      # optional seconds; default frame / fps
             "camera": {"location": [x, y, z],           # cm, Unreal world (Z up)
                        "rotation": [roll, pitch, yaw],  # degrees (FRotator)
                        "fov": 28.8,                     # horizontal, over the filmback width
                        "filmback": [36.0, 24.0],        # sensor width, height (mm)
                        "resolution": [64, 36]},         # output width, height (px)
             "transforms": {"AdvBin": {"location": [...], "rotation": [...],
                                       "scale": [1, 1, 1]},   # scale optional
                            "Car1": {...}},
             "environment": {...}}             # optional; merged over the top level

``ASSET`` is undream's asset JSON (``name``, ``mesh``, ``scale``, ``texture``,
``color``); a relative mesh path (or texture ``init`` image path) is resolved
against the export file's directory; the object's texture defaults to
undream's. ``ENVIRONMENT`` is undream's environment JSON. Transforms are the
actors' world transforms (actor root, ``T · R · S``); the camera pose is the
cine camera component's world pose.

Frames may be listed in any order; they are sorted by their number (numerically,
so "9" precedes "10"), which becomes :attr:`Frame.index`; duplicates are an
error. Every actor declared in ``object`` and ``actors`` must have a transform
in every frame, and no other actor may. Every error is a one-line
:class:`~undream.errors.BridgeError` naming the file and the field, e.g.
``drive_by.json: frames[3].camera.rotation[1]: must be finite, got nan``.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from undream.bridge.unreal import (
    ue_camera_optics,
    ue_to_canonical_camera,
    ue_to_canonical_object,
    ue_transform,
)
from undream.errors import BridgeError, SpecError
from undream.spec import ActorPose, Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec import _check
from undream.spec.io import read_json, resolve_against
from undream.spec.model import BUILTIN_PREFIX

FORMAT = "undream-unreal-export"
VERSION = 1
TOP_REQUIRED = ("format", "version", "fps", "object", "frames")
TOP_OPTIONAL = ("sequence", "name", "camera", "actors", "environment")
CAMERA_FIELDS = ("location", "rotation", "fov", "filmback", "resolution")
MAX_RESOLUTION = 16384
MAX_FRAME = 10**7


@dataclass(frozen=True)
class _Header:
    """What every frame needs: fps, actor labels → asset names, base environment."""

    fps: float
    object_actor: str
    actors: dict[str, str]
    environment: Mapping[str, Any]


def sequence_from_unreal(path: str | Path) -> Sequence:
    """Read an ``undream-unreal-export`` JSON file (see the module docstring).

    Positions in the file are Unreal centimetres (Z up) and rotations FRotator
    degrees; the result is canonical (Y up, metres) with ``source="unreal"``.
    Raises :class:`BridgeError` whose one-line message names the file and the
    field.
    """
    path = Path(path)
    data = _read_json(path)
    try:
        return _sequence(data, path)
    except (BridgeError, SpecError) as err:
        raise BridgeError(_one_line(f"{path}: {err}")) from None


def _read_json(path: Path) -> Any:
    """The export's JSON, read under undream's input limits (:func:`undream.spec.io.read_json`)."""
    try:
        return read_json(path)
    except SpecError as err:
        raise BridgeError(_one_line(str(err))) from None


def _one_line(msg: str) -> str:
    return " ".join(msg.splitlines())


# --- field checks; `where` is the dotted field path of the value -----------------

def _key(where: str, key: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_-]*", key):
        return f"{where}[{key!r}]"
    return f"{where}.{key}" if where else key


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _fail(where: str, expected: str, value: Any) -> BridgeError:
    return BridgeError(f"{where}: {expected}, got {_show(value)}")


def _at(where: str):
    """Prefix errors from the spec and bridge functions with the field path ``where``."""
    return _check.at(where, catch=(BridgeError, SpecError), raise_as=BridgeError)


def _fields(value: Any, where: str, required: tuple[str, ...], optional: tuple[str, ...]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise _fail(where or "export", "must be a JSON object", value)
    for k in required:
        if k not in value:
            raise BridgeError(f"{_key(where, k)}: is required")
    extra = sorted(set(value) - set(required) - set(optional))
    if extra:
        valid = ", ".join(sorted((*required, *optional)))
        raise BridgeError(f"{_key(where, str(extra[0]))}: unknown field (valid: {valid})")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(where, "must be a number", value)
    if not math.isfinite(value):
        raise _fail(where, "must be finite", value)
    return float(value)


def _positive(value: Any, where: str) -> float:
    v = _number(value, where)
    if v <= 0:
        raise _fail(where, "must be > 0", value)
    return v


def _numbers(value: Any, where: str, n: int) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise _fail(where, f"must be a list of {n} numbers", value)
    return tuple(_number(v, f"{where}[{i}]") for i, v in enumerate(value))


def _resolution(value: Any, where: str) -> tuple[int, int]:
    if not isinstance(value, list) or len(value) != 2:
        raise _fail(where, "must be [width, height] in pixels", value)
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_RESOLUTION:
            raise _fail(f"{where}[{i}]", f"must be an integer in [1, {MAX_RESOLUTION}]", v)
    return value[0], value[1]


def _frame_number(value: Any, where: str) -> int:
    number: int | None = None
    if isinstance(value, str) and value.isascii() and value.isdigit():
        number = int(value)
    elif isinstance(value, float) and value.is_integer():
        number = int(value)
    elif isinstance(value, int) and not isinstance(value, bool):
        number = value
    if number is None or not 0 <= number <= MAX_FRAME:
        raise _fail(where, f"must be a frame number in [0, {MAX_FRAME}] "
                           "(an integer, or a string of digits)", value)
    return number


def _label(value: Any, where: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _fail(where, "must be the actor's label (a non-empty string)", value)
    return value


# --- header -----------------------------------------------------------------------

def _sequence(data: Any, path: Path) -> Sequence:
    d = _fields(data, "", TOP_REQUIRED, TOP_OPTIONAL)
    if d["format"] != FORMAT:
        raise _fail("format", f"must be {FORMAT!r}", d["format"])
    if d["version"] != VERSION or isinstance(d["version"], bool):
        raise _fail("version", f"must be {VERSION}", d["version"])
    fps = _positive(d["fps"], "fps")
    if "camera" in d:
        _fields(d["camera"], "camera", (), ("name",))
    obj = _fields(d["object"], "object", ("actor", "asset"), ())
    label = _label(obj["actor"], "object.actor")
    asset = _asset(obj["asset"], "object.asset", path.parent, adversarial=True)
    labels, assets = _actors(d.get("actors", []), label, asset.name, path.parent)
    env = _environment(d.get("environment", {}), "environment")
    header = _Header(fps, label, dict(zip(labels, (a.name for a in assets))), env)
    frames = _frames(d["frames"], header)
    return Sequence(name=_name(d, path), asset=asset, frames=frames, actors=tuple(assets),
                    fps=fps, source="unreal")


def _name(d: Mapping[str, Any], path: Path) -> str:
    if "name" in d:
        return d["name"]  # validated by Sequence
    source = d.get("sequence")
    if source is not None and not isinstance(source, str):
        raise _fail("sequence", "must be the Level Sequence's asset path (a string)", source)
    stem = (source or path.stem).rstrip("/").rsplit("/", 1)[-1].split(".", 1)[0]
    return re.sub(r"[^A-Za-z0-9_-]", "_", stem) or "unreal"


def _resolve(value: Any, base: Path) -> Any:
    if isinstance(value, str) and value and not value.startswith(BUILTIN_PREFIX):
        return resolve_against(value, base, keep_absolute=True)
    return value


def _asset(value: Any, where: str, base: Path, adversarial: bool) -> Asset:
    if not isinstance(value, Mapping):
        raise _fail(where, "must be an asset JSON object", value)
    d = dict(value)
    if "mesh" in d:
        d["mesh"] = _resolve(d["mesh"], base)
    if adversarial and d.get("texture") is None:
        d["texture"] = TextureParam().to_json()
    if isinstance(d.get("texture"), Mapping) and isinstance(d["texture"].get("init"), str):
        d["texture"] = {**d["texture"], "init": _resolve(d["texture"]["init"], base)}
    with _at(where):
        return Asset.from_json(d)


def _actors(value: Any, object_label: str, object_name: str, base: Path) -> tuple[list[str], list[Asset]]:
    if not isinstance(value, list):
        raise _fail("actors", "must be a list", value)
    labels, assets = [], []
    for i, item in enumerate(value):
        where = f"actors[{i}]"
        a = _fields(item, where, ("actor", "asset"), ())
        label = _label(a["actor"], f"{where}.actor")
        if label == object_label or label in labels:
            raise _fail(f"{where}.actor", "must name each actor once (and not the object's)", label)
        asset = _asset(a["asset"], f"{where}.asset", base, adversarial=False)
        if asset.name == object_name or asset.name in (x.name for x in assets):
            raise _fail(f"{where}.asset.name", "must be unique among the assets", asset.name)
        labels.append(label)
        assets.append(asset)
    return labels, assets


def _environment(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise _fail(where, "must be an environment JSON object", value)
    with _at(where):
        Environment.from_json(value)
    return value


# --- frames -----------------------------------------------------------------------

def _frames(value: Any, header: _Header) -> tuple[Frame, ...]:
    if not isinstance(value, list) or not value:
        raise _fail("frames", "must be a non-empty list", value)
    seen: dict[int, int] = {}
    frames = []
    for i, raw in enumerate(value):
        frame = _frame(raw, f"frames[{i}]", header)
        if frame.index in seen:
            raise BridgeError(f"frames[{i}].frame: duplicate frame number {frame.index} "
                              f"(also frames[{seen[frame.index]}])")
        seen[frame.index] = i
        frames.append(frame)
    return tuple(sorted(frames, key=lambda f: f.index))


def _frame(raw: Any, where: str, header: _Header) -> Frame:
    d = _fields(raw, where, ("frame", "camera", "transforms"), ("time", "environment"))
    number = _frame_number(d["frame"], f"{where}.frame")
    time = _number(d["time"], f"{where}.time") if "time" in d else number / header.fps
    camera = _camera(d["camera"], f"{where}.camera")
    poses = _transforms(d["transforms"], f"{where}.transforms", header)
    env = {**header.environment, **_fields(d.get("environment", {}), f"{where}.environment", (),
                                           tuple(Environment.__dataclass_fields__))}
    with _at(f"{where}.environment"):
        environment = Environment.from_json(env)
    with _at(where):
        actors = tuple(ActorPose(name, poses[label]) for label, name in header.actors.items())
        return Frame(index=number, camera=camera, object_to_world=poses[header.object_actor],
                     environment=environment, actors=actors, time=time)


def _camera(value: Any, where: str) -> Camera:
    d = _fields(value, where, CAMERA_FIELDS, ())
    location = _numbers(d["location"], f"{where}.location", 3)
    rotation = _numbers(d["rotation"], f"{where}.rotation", 3)
    fov = _number(d["fov"], f"{where}.fov")
    if not 0 < fov < 180:
        raise _fail(f"{where}.fov", "must be the horizontal field of view in (0, 180) degrees", fov)
    filmback = _numbers(d["filmback"], f"{where}.filmback", 2)
    for i, v in enumerate(filmback):
        _positive(v, f"{where}.filmback[{i}]")
    resolution = _resolution(d["resolution"], f"{where}.resolution")
    with _at(where):
        to_world = ue_to_canonical_camera(ue_transform(location, rotation))
        fov_c, res, film = ue_camera_optics(fov, filmback[0] / filmback[1], resolution)
        return Camera(Transform.from_rows(to_world), fov_c, res, film)


def _transforms(value: Any, where: str, header: _Header) -> dict[str, Transform]:
    if not isinstance(value, Mapping):
        raise _fail(where, "must map actor labels to transforms", value)
    declared = [header.object_actor, *header.actors]
    for label in declared:
        if label not in value:
            raise BridgeError(f"{where}: missing actor {label!r}")
    for label in value:
        if label not in declared:
            raise BridgeError(f"{where}: unknown actor {label!r} (declared: {', '.join(declared)})")
    return {label: _transform(value[label], _key(where, label)) for label in declared}


def _transform(value: Any, where: str) -> Transform:
    d = _fields(value, where, ("location", "rotation"), ("scale",))
    location = _numbers(d["location"], f"{where}.location", 3)
    rotation = _numbers(d["rotation"], f"{where}.rotation", 3)
    scale = _numbers(d["scale"], f"{where}.scale", 3) if "scale" in d else (1.0, 1.0, 1.0)
    with _at(where):
        return Transform.from_rows(ue_to_canonical_object(ue_transform(location, rotation, scale)))
