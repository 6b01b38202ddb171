"""Export a ``.blend`` file's camera path and one object as JSON (runs in Blender's Python, ``bpy`` 5.0.1).

``python -m undream.bridge.blender_export FILE.blend --object NAME [--camera NAME] [--actor NAME ...]
--out EXPORT.json``

Started by :func:`undream.bridge.blender_import.sequence_from_blend` in
``.venv-blender`` (Blender needs numpy < 2, undream numpy 2); it only reads
Blender's own values and writes them, unconverted, for the main process to
validate and convert (:mod:`undream.bridge.blender_import` documents the
format). For every frame from the scene's ``frame_start`` to ``frame_end``
(every ``frame_step``) it sets the frame, so Blender evaluates every
animation (keys, drivers, constraints, parents), and reads the camera's and
the object's world matrices (Blender world: Z up, metres) and the camera's
view frame (``Camera.view_frame``: the image rectangle's corners in the
camera's local frame, which looks along −Z, +Y up, +X right; sensor fit,
lens and aspect ratio included). The object's mesh is read once, at the first
frame, with its modifiers applied, in its local frame: triangle corners with
their UV (the active render UV map; Blender's v runs up) and normal. Objects
named with ``--actor`` (occluders, other traffic) are read the same way,
UVs optional, their world matrices every frame.

A problem Blender can see (no such object, not a mesh, no UV map, no camera)
is written as ``{"error": "one line"}``; nothing else is written then.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

FORMAT = "undream-blender-export"
VERSION = 1


class ExportError(Exception):
    """Something in the .blend file that undream cannot import (one line)."""


def _matrix(m: Any) -> list[list[float]]:
    return [[float(v) for v in row] for row in m]


def _names(collection: Any, kind: str | None = None) -> str:
    names = sorted(o.name for o in collection if kind is None or o.type == kind)
    return ", ".join(names[:12]) + (", ..." if len(names) > 12 else "") if names else "none"


def _find_object(bpy: Any, name: str, need_uvs: bool = True) -> Any:
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise ExportError(f"no object named {name!r} (mesh objects: {_names(bpy.data.objects, 'MESH')})")
    if obj.type != "MESH":
        raise ExportError(f"object {name!r} is a {obj.type}, not a mesh")
    if need_uvs and not obj.data.uv_layers:
        raise ExportError(f"object {name!r} has no UV map; undream needs a UV-mapped mesh to place the "
                          "adversarial texture (add one in Blender: UV > Unwrap)")
    return obj


def _find_camera(bpy: Any, scene: Any, name: str | None) -> Any:
    cam = bpy.data.objects.get(name) if name else scene.camera
    if cam is None:
        raise ExportError(f"no camera named {name!r} (cameras: {_names(bpy.data.objects, 'CAMERA')})" if name
                          else "the scene has no active camera (set one, or name it with --camera)")
    if cam.type != "CAMERA":
        raise ExportError(f"object {cam.name!r} is a {cam.type}, not a camera")
    return cam


def _mesh(bpy: Any, obj: Any, need_uvs: bool = True) -> dict[str, Any]:
    """Triangle corners of the evaluated mesh in the object's local frame (Blender axes); UVs (0, 0)
    where ``need_uvs`` is False and the mesh has none."""
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    me = evaluated.to_mesh()
    try:
        layer = next((uv for uv in me.uv_layers if uv.active_render), me.uv_layers.active)
        if layer is None and need_uvs:
            raise ExportError(f"object {obj.name!r} has no UV map after its modifiers")
        me.calc_loop_triangles()
        tris = me.loop_triangles
        if not len(tris):
            raise ExportError(f"object {obj.name!r} has no faces")
        normals = me.corner_normals
        return {"vertices": [list(v.co) for v in me.vertices],
                "triangles": [list(t.vertices) for t in tris],
                "uvs": [[list(layer.uv[i].vector) if layer else [0.0, 0.0] for i in t.loops] for t in tris],
                "normals": [[list(normals[i].vector) for i in t.loops] for t in tris],
                "uv_map": layer.name if layer else None}
    finally:
        evaluated.to_mesh_clear()


def export(blend: str, object_name: str, camera_name: str | None = None,
           actor_names: Sequence[str] = ()) -> dict[str, Any]:
    """Everything undream needs from ``blend`` (see the module docstring); :class:`ExportError` otherwise."""
    import bpy

    bpy.ops.wm.open_mainfile(filepath=blend)
    scene = bpy.context.scene
    obj = _find_object(bpy, object_name)
    actors = [_find_object(bpy, name, need_uvs=False) for name in actor_names]
    if object_name in actor_names or len(set(actor_names)) != len(actor_names):
        raise ExportError(f"--actor names each object once, and not the adversarial object {object_name!r}")
    cam = _find_camera(bpy, scene, camera_name)
    if cam.data.type != "PERSP":
        raise ExportError(f"camera {cam.name!r} is {cam.data.type}; undream needs a perspective camera")
    r = scene.render
    frames_n = range(scene.frame_start, scene.frame_end + 1, max(scene.frame_step, 1))
    scene.frame_set(scene.frame_start)
    out: dict[str, Any] = {
        "format": FORMAT, "version": VERSION, "blend": blend, "blender": bpy.app.version_string,
        "scene": scene.name, "fps": r.fps / r.fps_base,
        "resolution": [r.resolution_x * r.resolution_percentage // 100,
                       r.resolution_y * r.resolution_percentage // 100],
        "pixel_aspect": [r.pixel_aspect_x, r.pixel_aspect_y],
        "camera": {"name": cam.name}, "object": {"name": obj.name, "mesh": _mesh(bpy, obj)},
        "actors": [{"name": a.name, "mesh": _mesh(bpy, a, need_uvs=False)} for a in actors], "frames": []}
    for f in frames_n:
        scene.frame_set(f)
        out["frames"].append({
            "frame": f,
            "camera": {"matrix_world": _matrix(cam.matrix_world),
                       "view_frame": [list(v) for v in cam.data.view_frame(scene=scene)]},
            "object": {"matrix_world": _matrix(obj.matrix_world)},
            "actors": {a.name: {"matrix_world": _matrix(a.matrix_world)} for a in actors}})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("blend")
    parser.add_argument("--object", required=True)
    parser.add_argument("--camera", default=None)
    parser.add_argument("--actor", action="append", default=[])
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    try:
        data = export(str(Path(args.blend).resolve()), args.object, args.camera, args.actor)
    except ExportError as err:
        data = {"error": str(err)}
    except Exception as err:  # Blender's own errors (a file it cannot read): one line for the user
        data = {"error": " ".join(f"{type(err).__name__}: {err}".split())}
    Path(args.out).write_text(json.dumps(data))
    return 3 if "error" in data else 0


if __name__ == "__main__":
    sys.exit(main())
