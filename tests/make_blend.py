"""Build a tiny .blend for tests/test_blender_import.py (runs in Blender's Python: ``python make_blend.py OUT.blend``).

The scene: 48×36 px, 10 fps, frames 1–5; a keyframed perspective camera ``Cam``
(vertical sensor fit, so the horizontal field of view must come from the
aspect ratio) that moves and turns; ``Crate``, a UV-mapped box, scaled,
moving and turning; ``Bare``, a plane without UVs; ``Flat``, an orthographic
camera. Next to OUT.blend it writes OUT.json: for every frame, Blender's own
``world_to_camera_view`` of the crate's origin and of its 8 corners, as
pixel coordinates (x right, y down, origin at the image's top-left corner).
"""
import json
import math
import sys

import bpy
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector

W, H = 48, 36


def aim(obj, target):
    direction = Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def main(out):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = W, H, 100
    scene.render.fps, scene.render.fps_base = 10, 1.0
    scene.frame_start, scene.frame_end = 1, 5

    bpy.ops.mesh.primitive_cube_add(size=1.0)
    crate = bpy.context.active_object
    crate.name = "Crate"
    crate.scale = (1.0, 0.6, 0.8)
    for frame, loc, yaw in ((1, (0.0, 0.0, 0.4), 0.0), (5, (0.8, 0.6, 0.5), 50.0)):
        crate.location = loc
        crate.rotation_euler = (0.0, math.radians(10.0), math.radians(yaw))
        crate.keyframe_insert("location", frame=frame)
        crate.keyframe_insert("rotation_euler", frame=frame)

    bpy.ops.mesh.primitive_cube_add(size=1.0)
    post = bpy.context.active_object
    post.name = "Post"
    post.scale = (0.15, 0.15, 1.2)
    while post.data.uv_layers:
        post.data.uv_layers.remove(post.data.uv_layers[0])
    for frame, loc in ((1, (1.5, -2.0, 0.6)), (5, (-1.0, -1.5, 0.6))):
        post.location = loc
        post.keyframe_insert("location", frame=frame)

    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(3.0, 3.0, 0.0))
    bare = bpy.context.active_object
    bare.name = "Bare"
    while bare.data.uv_layers:
        bare.data.uv_layers.remove(bare.data.uv_layers[0])

    cam_data = bpy.data.cameras.new("Cam")
    cam_data.sensor_fit = "VERTICAL"
    cam_data.sensor_height = 20.0
    cam_data.lens = 28.0
    cam = bpy.data.objects.new("Cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    for frame, loc, target in ((1, (4.0, -5.0, 2.5), (0.0, 0.0, 0.4)), (5, (-1.5, -6.0, 3.5), (0.5, 0.3, 0.6))):
        cam.location = loc
        aim(cam, target)
        cam.keyframe_insert("location", frame=frame)
        cam.keyframe_insert("rotation_euler", frame=frame)

    flat_data = bpy.data.cameras.new("Flat")
    flat_data.type = "ORTHO"
    flat = bpy.data.objects.new("Flat", flat_data)
    scene.collection.objects.link(flat)

    expected = []
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        points = [crate.matrix_world.translation.copy()]
        points += [crate.matrix_world @ Vector((x, y, z)) for x in (-0.5, 0.5) for y in (-0.5, 0.5)
                   for z in (-0.5, 0.5)]
        pixels = []
        for p in points:
            v = world_to_camera_view(scene, cam, p)
            pixels.append([v.x * W, (1.0 - v.y) * H])
        posts = [world_to_camera_view(scene, cam, post.matrix_world @ Vector((x, y, z)))
                 for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]
        expected.append({"frame": frame, "origin": pixels[0], "corners": pixels[1:],
                         "post": [[v.x * W, (1.0 - v.y) * H] for v in posts]})
    bpy.ops.wm.save_as_mainfile(filepath=out)
    with open(out[:-len(".blend")] + ".json", "w") as f:
        json.dump(expected, f)


if __name__ == "__main__":
    main(sys.argv[-1])
