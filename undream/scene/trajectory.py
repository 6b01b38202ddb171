"""Native trajectory specs (YAML) → canonical :class:`~undream.spec.Sequence`.

A spec names the frames, the camera path, the adversarial object and its
path, extra actors with theirs, and the environment. Path types, for the
camera and any object alike (positions in metres, canonical Y up)::

    static     position
    orbit      center, radius, height (above center), start_deg, end_deg
               (azimuth about +Y; 0° is +Z of the centre, 90° is +X)
    dolly      start, end                 (straight line; alias: drive_by)
    flyover    start, end, altitude       (straight line at that height)
    keyframes  keys: [{frame, position, look_at | yaw | rotation}], interpolation: cubic | linear

Cameras look at ``look_at`` (a point, or ``object``, the default: the
adversarial object's origin plus ``look_at_offset``). Objects turn by ``yaw``
(degrees about +Y), ``rotation`` ([x, y, z] degrees, extrinsic XYZ), or with
``heading: motion`` along their direction of travel (the default for moving
paths). Parametric paths run from the first frame (u = 0) to the last (u = 1).
An asset's ``mesh`` and its texture's ``init`` may name an object fetched at
setup, ``asset:NAME`` (:mod:`undream.scene.fetched`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from undream.errors import SpecError
from undream.scene import fetched, poses
from undream.spec import ActorPose, Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec import _check as c
from undream.spec.io import resolve_against
from undream.spec.limits import bounded

PATH_TYPES = ("static", "orbit", "dolly", "drive_by", "flyover", "keyframes")
TOP_FIELDS = {"name", "seed", "frames", "fps", "camera", "object", "actors", "environment"}


def sequence_from_trajectory(spec: Mapping[str, Any], base_dir: Path | None = None,
                             cache_dir: str | Path | None = None) -> Sequence:
    """Build a sequence from a parsed trajectory spec (see the module docstring). ``cache_dir``:
    undream's cache folder, where ``asset:NAME`` meshes and textures are
    (:func:`undream.scene.fetched.resolve`); the edge passes it from its settings."""
    spec = c.mapping("spec", spec)
    c.no_extra(spec, TOP_FIELDS)
    n = bounded("frames", c.require(spec, "frames"))
    fps = c.positive("fps", spec.get("fps", 10.0))
    obj = c.mapping("object", c.require(spec, "object"))
    with c.at("object"):
        asset = _asset(c.require(obj, "asset"), base_dir, adversarial=True, cache_dir=cache_dir)
        obj_poses = _object_path(obj, n)
    actors, actor_poses = [], []
    actor_specs = spec.get("actors")
    if actor_specs is not None and not isinstance(actor_specs, list):
        raise c.fail("actors", actor_specs, "must be a list of actors ({asset, path, ...} each)")
    for i, a in enumerate(actor_specs or []):
        with c.at(f"actors[{i}]"):
            a = c.mapping("actor", a)
            actors.append(_asset(c.require(a, "asset"), base_dir, adversarial=False, cache_dir=cache_dir))
            actor_poses.append(_object_path(a, n))
    with c.at("camera"):
        cams = _cameras(c.mapping("camera", c.require(spec, "camera")), n, obj_poses)
    envs = _environments(spec.get("environment", {}), n, base_dir)
    frames = tuple(
        Frame(index=i, time=i / fps, camera=cams[i],
              object_to_world=Transform.from_rows(obj_poses[i]), environment=envs[i],
              actors=tuple(ActorPose(a.name, Transform.from_rows(p[i])) for a, p in zip(actors, actor_poses)))
        for i in range(n))
    return Sequence(name=spec.get("name", "sequence"), asset=asset, frames=frames,
                    actors=tuple(actors), fps=fps, source="trajectory", seed=spec.get("seed", 0))


def _asset(d: Any, base_dir: Path | None, adversarial: bool, cache_dir: str | Path | None = None) -> Asset:
    with c.at("asset"):
        d = dict(c.mapping("asset", d))
        if adversarial and d.get("texture") is None:
            d["texture"] = TextureParam().to_json()
        mesh = d.get("mesh")
        if fetched.is_fetched(mesh):
            d["mesh"] = fetched.resolve(mesh, "mesh", cache_dir=cache_dir)
        elif isinstance(mesh, str) and not mesh.startswith("builtin:") and base_dir is not None:
            d["mesh"] = resolve_against(mesh, base_dir, keep_absolute=True)
        tex = d.get("texture")
        if isinstance(tex, Mapping) and fetched.is_fetched(tex.get("init")):
            d["texture"] = {**tex, "init": fetched.resolve(tex["init"], "texture.init", kind="texture", cache_dir=cache_dir)}
        return Asset.from_json(d)


def _cameras(d: Mapping[str, Any], n: int, obj_poses: np.ndarray) -> list[Camera]:
    c.no_extra(d, {"fov", "resolution", "film", "path", "look_at", "look_at_offset", "up"})
    fov = c.finite("fov", c.require(d, "fov"))
    if not 0 < fov < 180:
        raise c.fail("fov", fov, "must be the horizontal field of view in (0, 180) degrees")
    res = c.ints("resolution", c.require(d, "resolution"), 2, 1, 16384)
    film = c.ints("film", d["film"], 2, 1, 16384) if d.get("film") is not None else None
    path = c.mapping("path", c.require(d, "path"))
    with c.at("path"):
        positions = _positions(path, n)
    targets = _targets(d, path, n, obj_poses)
    up = _up(d.get("up"))
    cams = []
    for i in range(n):
        m = poses.look_at(positions[i], targets[i], field=f"look_at (frame {i})", **up)
        cams.append(Camera(Transform.from_rows(m), fov, res, film))
    return cams


def _up(value: Any) -> dict[str, Any]:
    """``look_at``'s keywords for the camera's ``up`` (default: world +Y, with a fallback where the
    camera looks straight along it); a given ``up`` must be non-zero and is never replaced."""
    if value is None:
        return {}
    up = np.array(c.vector("up", value, 3))
    if not np.linalg.norm(up) > 1e-9:
        raise c.fail("up", value, "must be a non-zero vector (the camera's up direction)")
    return {"up": up / np.linalg.norm(up), "strict": True}


def _targets(d: Mapping[str, Any], path: Mapping[str, Any], n: int, obj_poses: np.ndarray) -> np.ndarray:
    if path.get("type") == "keyframes" and any("look_at" in k for k in _keys(path)):
        with c.at("path"):
            return _keyframed(path, n, "look_at")
    look = d.get("look_at", "object")
    offset = np.array(c.point("look_at_offset", d.get("look_at_offset", [0, 0.5, 0])))
    if look == "object":
        return obj_poses[:, :3, 3] + offset
    return np.tile(np.array(c.point("look_at", look)), (n, 1))


def _object_path(d: Mapping[str, Any], n: int) -> np.ndarray:
    c.no_extra(d, {"asset", "path", "yaw", "rotation", "heading"})
    path = c.mapping("path", d.get("path", {"type": "static", "position": [0, 0, 0]}))
    with c.at("path"):
        positions = _positions(path, n)
        rots = _rotations(d, path, positions, n)
    return np.stack([poses.object_pose(positions[i], rots[i]) for i in range(n)])


def _rotations(d: Mapping[str, Any], path: Mapping[str, Any], positions: np.ndarray, n: int) -> Rotation:
    if path.get("type") == "keyframes" and any(("yaw" in k or "rotation" in k) for k in _keys(path)):
        return _keyframed_rotations(path, n)
    base = Rotation.from_euler("xyz", c.vector("rotation", d["rotation"], 3), degrees=True) \
        if "rotation" in d else poses.yaw_rotation(c.finite("yaw", d.get("yaw", 0.0)))
    moving = path.get("type", "static") != "static"
    heading = c.choice("heading", d.get("heading", "motion" if moving else "fixed"), ("motion", "fixed"))
    if heading == "fixed" or n == 1:
        return Rotation.concatenate([base] * n)
    vel = np.gradient(positions, axis=0)
    yaws, last = [], 0.0
    for v in vel:
        if np.hypot(v[0], v[2]) > 1e-9:
            last = poses.heading_yaw(v)
        yaws.append(last)
    return Rotation.concatenate([poses.yaw_rotation(y) * base for y in yaws])


def _positions(path: Mapping[str, Any], n: int) -> np.ndarray:
    kind = c.choice("type", c.require(path, "type"), PATH_TYPES)
    u = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    if kind == "static":
        c.no_extra(path, {"type", "position"})
        return np.tile(np.array(c.point("position", c.require(path, "position"))), (n, 1))
    if kind == "orbit":
        c.no_extra(path, {"type", "center", "radius", "height", "start_deg", "end_deg"})
        center = np.array(c.point("center", path.get("center", [0, 0, 0])))
        r = c.length("radius", c.require(path, "radius"))
        h = c.length("height", path.get("height", 0.0), signed=True)
        a0 = c.finite("start_deg", path.get("start_deg", 0.0))
        a1 = c.finite("end_deg", path.get("end_deg", 360.0 * (n - 1) / max(n, 1)))
        az = np.radians(a0 + (a1 - a0) * u)
        return center + np.stack([r * np.sin(az), np.full(n, h), r * np.cos(az)], axis=1)
    if kind in ("dolly", "drive_by", "flyover"):
        allowed = {"type", "start", "end"} | ({"altitude"} if kind == "flyover" else set())
        c.no_extra(path, allowed)
        p0 = np.array(c.point("start", c.require(path, "start")))
        p1 = np.array(c.point("end", c.require(path, "end")))
        if kind == "flyover":
            p0[1] = p1[1] = c.length("altitude", c.require(path, "altitude"))
        return p0 + (p1 - p0) * u[:, None]
    return _keyframed(path, n, "position")


def _keys(path: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """The keyframes that are mappings (a malformed ``keys`` is reported by :func:`_key_frames`)."""
    keys = path.get("keys")
    return [k for k in keys if isinstance(k, Mapping)] if isinstance(keys, list) else []


def _key_frames(path: Mapping[str, Any], n: int) -> tuple[list[Mapping[str, Any]], np.ndarray]:
    c.no_extra(path, {"type", "keys", "interpolation"})
    keys = path.get("keys")
    if not isinstance(keys, list) or len(keys) < 2:
        raise c.fail("keys", keys, "must be a list of at least 2 keyframes")
    frames = []
    for i, k in enumerate(keys):
        with c.at(f"keys[{i}]"):
            k = c.mapping("key", k)
            c.no_extra(k, {"frame", "position", "look_at", "yaw", "rotation"})
            frames.append(c.integer("frame", c.require(k, "frame"), 0, n - 1))
    if frames != sorted(set(frames)):
        raise c.fail("keys", frames, "must have strictly increasing frame numbers")
    return keys, np.array(frames, float)


def _keyframed(path: Mapping[str, Any], n: int, field: str) -> np.ndarray:
    keys, t = _key_frames(path, n)
    vals = []
    for i, k in enumerate(keys):
        with c.at(f"keys[{i}]"):
            vals.append(c.point(field, c.require(k, field)))
    kind = c.choice("interpolation", path.get("interpolation", "cubic"), ("cubic", "linear"))
    x = np.arange(n, dtype=float)
    v = np.array(vals)
    if kind == "linear":
        return np.stack([np.interp(x, t, v[:, j]) for j in range(3)], axis=1)
    spline = CubicSpline(t, v, bc_type="natural")
    return np.where((x < t[0])[:, None], v[0], np.where((x > t[-1])[:, None], v[-1], spline(x)))


def _keyframed_rotations(path: Mapping[str, Any], n: int) -> Rotation:
    keys, t = _key_frames(path, n)
    rots = []
    for i, k in enumerate(keys):
        with c.at(f"keys[{i}]"):
            if "rotation" in k:
                rots.append(Rotation.from_euler("xyz", c.vector("rotation", k["rotation"], 3), degrees=True))
            else:
                rots.append(poses.yaw_rotation(c.finite("yaw", k.get("yaw", 0.0))))
    x = np.clip(np.arange(n, dtype=float), t[0], t[-1])
    return RotationSpline(t, Rotation.concatenate(rots))(x)


def _environments(d: Any, n: int, base_dir: Path | None = None) -> list[Environment]:
    if isinstance(d, list):
        if len(d) != n:
            raise c.fail("environment", f"{len(d)} entries", f"must be one mapping or a list of {n} (one per frame)")
        out = []
        for i, e in enumerate(d):
            with c.at(f"environment[{i}]"):
                out.append(Environment.from_json(_resolve_envmap(e, base_dir)))
        return out
    with c.at("environment"):
        env = Environment.from_json(_resolve_envmap(d, base_dir))
    return [env] * n


def _resolve_envmap(d: Any, base_dir: Path | None) -> Any:
    """A relative ``envmap`` path resolved against the spec's folder, as mesh paths are."""
    if not isinstance(d, Mapping) or not isinstance(d.get("envmap"), str) or base_dir is None:
        return d
    return {**d, "envmap": resolve_against(Path(d["envmap"]), base_dir, keep_absolute=True)}
