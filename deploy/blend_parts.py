"""Export a .blend's UV-mapped mesh objects and packed images, for deploy/fetch_assets.py.

Runs in Blender's own interpreter (``.venv-blender/bin/python``, bpy 5.0.1)::

    .venv-blender/bin/python deploy/blend_parts.py FILE.blend OUT_DIR

Writes ``OUT_DIR/parts.npz``: for every mesh object with a UV layer, its
evaluated mesh (modifiers such as the armature applied, so a rigged person is
in the pose the file shows) in Blender's world frame (right-handed, Z up,
metres): ``NAME.vertices`` float64 (N, 3), ``NAME.triangles`` int64 (M, 3),
``NAME.uvs`` float64 (M, 3, 2) per corner (v up, Blender's), ``NAME.normals``
float64 (M, 3, 3) per corner; and ``OUT_DIR/images/NAME`` with the bytes of
every packed image, as packed. ``OUT_DIR/parts.json`` lists the objects with
their materials. The caller converts frames and flips v.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy  # noqa: F401 (Blender's interpreter only)
import numpy as np


def export(blend: str, out: Path) -> None:
    bpy.ops.wm.open_mainfile(filepath=blend)
    (out / "images").mkdir(parents=True, exist_ok=True)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    arrays, listing = {}, {}
    for obj in bpy.data.objects:
        if obj.type != "MESH" or not obj.data.uv_layers:
            continue
        ev = obj.evaluated_get(depsgraph)
        me = ev.to_mesh()
        me.calc_loop_triangles()
        world = np.array(ev.matrix_world, dtype=np.float64)
        verts = np.array([v.co for v in me.vertices], dtype=np.float64)
        verts = verts @ world[:3, :3].T + world[:3, 3]
        loops = np.array([t.loops[:] for t in me.loop_triangles], dtype=np.int64)
        loop_vert = np.array([lp.vertex_index for lp in me.loops], dtype=np.int64)
        uv = np.array([d.uv for d in me.uv_layers.active.data], dtype=np.float64)
        nrm = np.array([n.vector for n in me.corner_normals], dtype=np.float64)
        nrm = nrm @ np.linalg.inv(world[:3, :3])
        arrays[f"{obj.name}.vertices"] = verts
        arrays[f"{obj.name}.triangles"] = loop_vert[loops]
        arrays[f"{obj.name}.uvs"] = uv[loops]
        arrays[f"{obj.name}.normals"] = nrm[loops]
        listing[obj.name] = {"materials": [m.name if m else None for m in me.materials],
                             "vertices": len(verts), "triangles": len(loops)}
        ev.to_mesh_clear()
    for img in bpy.data.images:
        if img.packed_file is not None:
            (out / "images" / img.name).write_bytes(bytes(img.packed_file.data))
    np.savez(out / "parts.npz", **arrays)
    (out / "parts.json").write_text(json.dumps({"blend": blend, "blender": bpy.app.version_string,
                                                "objects": listing}, indent=1))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: blend_parts.py FILE.blend OUT_DIR")
    export(sys.argv[1], Path(sys.argv[2]))
