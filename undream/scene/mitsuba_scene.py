"""The one adapter from the scene model to Mitsuba scene dictionaries.

Three views of a frame share one sensor and one object node:

- ``sim``: everything the simulator shows (environment, fog, ground, props,
  object, actors), path traced (``volpath`` in fog and in the haze of rain
  and snow; scene directories hold it in :func:`with_haze`'s form, for the
  ``haze`` integrator, which computes volpath's estimate at about half its cost);
- ``grad``: no more than the object's appearance needs: the object, the
  emitters, and what can shadow or hide it (ground, actors), for ``prb``
  with direct light only (``max_depth`` 2), so a texel reaches the image only
  where the camera sees it;
- ``mask``: the object as the only (unit) emitter behind every occluder of
  the simulation scene, for its visible pixels.

The adversarial texture is a float ``bitmap`` with ``raw = true``: it holds
*linear* reflectance (convert sRGB → linear before writing it), which keeps it
differentiable (Mitsuba ≥ 3.9 does not differentiate 8-bit bitmaps).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from undream.scene import background, environment
from undream.scene.layout import mesh_name
from undream.scene.xml import Default, Mat4, UVScale
from undream.spec import Frame, Sequence

OBJECT_ID = "object"
KINDS = ("sim", "grad", "mask")
SIM_MAX_DEPTH = 6
GRAD_MAX_DEPTH = 2  # direct light only: the texture reaches the image through visible texels alone


@dataclass(frozen=True)
class ScenePaths:
    """Where a scene's files are, as the scene file will name them."""

    root: str  # the scene directory, relative to the XML file ("..") or absolute

    def mesh(self, name: str, index: int | None = None) -> str:
        """``meshes/NAME.ply``, or ``meshes/NAME_NNNN.ply``: frame ``index``'s file of a per-frame mesh."""
        return f"{self.root}/meshes/{name if index is None else mesh_name(name, index)}.ply"

    def texture(self, name: str) -> str:
        return f"{self.root}/textures/{name}.exr"

    def envmap(self, path: str) -> str:
        """An environment map's path: relative ones (``textures/envmap.exr``) are inside the scene directory."""
        return path if os.path.isabs(path) else f"{self.root}/{path}"


def _rgb(v: Any) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(x) for x in v]}


def sensor(frame: Frame, rfilter: str = "gaussian") -> dict[str, Any]:
    cam = frame.camera
    fw, fh = cam.film_size
    film: dict[str, Any] = {"type": "hdrfilm", "width": fw, "height": fh, "pixel_format": "rgb",
                            "rfilter": {"type": rfilter}}
    if cam.film is not None:
        ox, oy = cam.crop_offset
        film.update(crop_offset_x=ox, crop_offset_y=oy, crop_width=cam.resolution[0],
                    crop_height=cam.resolution[1])
    return {"type": "perspective", "fov": cam.fov_deg, "fov_axis": "x", "near_clip": 0.01,
            "far_clip": 1000.0, "to_world": Mat4.of(cam.to_world.matrix),
            "sampler": {"type": "independent", "sample_count": Default("spp", 16)}, "film": film}


def texture_node(seq: Sequence, paths: ScenePaths) -> dict[str, Any]:
    tex = seq.texture
    return {"type": "bitmap", "filename": paths.texture(tex.name), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "repeat", "to_uv": UVScale(*tex.uv_scale)}


def _object(seq: Sequence, frame: Frame, paths: ScenePaths, kind: str) -> dict[str, Any]:
    index = frame.index if seq.asset.per_frame else None
    node: dict[str, Any] = {"type": "ply", "filename": paths.mesh(OBJECT_ID, index),
                            "to_world": Mat4.of(frame.object_to_world.matrix)}
    if kind == "mask":
        node["bsdf"] = {"type": "diffuse", "reflectance": _rgb((0, 0, 0))}
        node["emitter"] = {"type": "area", "radiance": _rgb((1, 1, 1))}
    else:
        node["bsdf"] = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": texture_node(seq, paths)}}
    return node


def _occluder(node: dict[str, Any], kind: str) -> dict[str, Any]:
    """Black for the mask, plain grey for the gradient scene, as is for the simulation."""
    if kind == "sim":
        return node
    grey = (0.0, 0.0, 0.0) if kind == "mask" else (0.3, 0.3, 0.3)
    return {**node, "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": _rgb(grey)}}}


def scene_dict(seq: Sequence, frame: Frame, paths: ScenePaths, kind: str) -> dict[str, Any]:
    """The Mitsuba scene dictionary of ``frame`` for ``kind`` in :data:`KINDS`."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    env = frame.environment
    fog = kind == "sim" and environment.has_medium(env)
    d: dict[str, Any] = {"type": "scene"}
    if kind == "mask":
        d["integrator"] = {"type": "path", "max_depth": 1}
    elif kind == "grad":
        d["integrator"] = {"type": "prb", "max_depth": GRAD_MAX_DEPTH}
    else:
        d["integrator"] = {"type": "volpath" if fog else "path", "max_depth": SIM_MAX_DEPTH}
    d["sensor"] = sensor(frame, "box" if kind == "mask" else "gaussian")
    anchor = np.array(frame.object_to_world.translation)
    if kind != "mask":
        d.update(environment.emitters(env, anchor, None if env.envmap is None else paths.envmap(env.envmap)))
    if fog:
        d["fog"] = environment.fog_medium(env)
        d["sensor"]["medium"] = {"type": "ref", "id": "fog"}
        d["fog_volume"] = _fog_volume(frame, anchor)
    d["ground"] = _occluder(background.ground(env.background, lambda c: environment.ground_tint(env, c)), kind)
    d[OBJECT_ID] = _object(seq, frame, paths, kind)
    for asset, pose in _actor_poses(seq, frame):
        index = frame.index if asset.per_frame else None
        node = {"type": "ply", "filename": paths.mesh(asset.name, index), "to_world": Mat4.of(pose.to_world.matrix),
                "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": _rgb(asset.color)}}}
        d[f"actor_{asset.name}"] = _occluder(node, kind)
    if kind != "grad":
        for i, p in enumerate(background.props(seq, env.background)):
            node = {"type": p.shape, "to_world": Mat4.of(p.to_world),
                    "bsdf": {"type": "diffuse", "reflectance": _rgb(p.colour)}}
            d[f"prop_{i:02d}"] = _occluder(node, kind)
    return d


def with_haze(d: dict[str, Any]) -> dict[str, Any]:
    """``d`` with its medium rendered by the ``haze`` integrator (:mod:`undream.render.haze`), as scene
    directories hold it: the fog's medium, its null sphere and the sensor's medium become the
    integrator's parameters (volpath's light transport at about half its cost). ``d`` without a medium
    is returned as it is; Blender's adapter reads the medium from :func:`scene_dict` itself."""
    if "fog" not in d:
        return d
    fog, volume = d["fog"], d["fog_volume"]
    out = {k: v for k, v in d.items() if k not in ("fog", "fog_volume")}
    out["sensor"] = {k: v for k, v in d["sensor"].items() if k != "medium"}
    out["integrator"] = {"type": "haze", "max_depth": d["integrator"]["max_depth"],
                         "sigma_t": float(fog["sigma_t"]) * float(fog.get("scale", 1.0)), "albedo": fog["albedo"],
                         "center": list(volume["center"]), "radius": float(volume["radius"])}
    return out


def _actor_poses(seq: Sequence, frame: Frame):
    assets = {a.name: a for a in seq.actors}
    return [(assets[p.name], p) for p in frame.actors]


def _fog_volume(frame: Frame, anchor: np.ndarray) -> dict[str, Any]:
    """A null-surfaced sphere holding the fog, around the camera and the object."""
    cam = np.array(frame.camera.to_world.translation)
    r = float(np.linalg.norm(cam - anchor)) + 40.0
    return {"type": "sphere", "center": anchor.tolist(), "radius": r, "bsdf": {"type": "null"},
            "interior": {"type": "ref", "id": "fog"}}
