"""A scene directory as a Blender Cycles scene (runs inside Blender's Python, ``bpy`` 5.0.1).

The Blender scene is a translation of the very Mitsuba *simulation* scene
dictionaries that :func:`undream.scene.mitsuba_scene.scene_dict` builds per
frame (sensor, sun/sky/lamp, fog, ground, object, actors, props), so both
simulators show the same canonical sequence. Objects are built once; a frame
only moves them, hides the ones it lacks and sets its lights. The adversarial
texture is one float image whose pixels are replaced before each render.

Conventions:

- Canonical (Mitsuba) world: right-handed, Y up, metres. Blender: Z up. A
  point maps by ``C = [[1,0,0],[0,0,-1],[0,1,0]]`` (x → x, y → z, z → −y),
  so an object's Blender world matrix is ``C4 @ M`` (mesh data stays in the
  canonical local frame). Mitsuba's camera looks along local +Z with +X to
  the image's left; Blender's along −Z with +X to the right: the camera's
  matrix is ``C4 @ M @ diag(−1, 1, −1, 1)``. Matrices only, no Euler angles.
- UVs: Mitsuba's ``v`` runs down the texture's rows (row 0 at v = 0);
  Blender's runs up. Blender UVs are ``(su·u, 1 − sv·v)`` (``to_uv`` scale
  baked in) and the image holds the texture's rows bottom-up.
- Colour: every value is linear Rec.709 (Blender's scene-linear space, the
  primaries of Mitsuba's ``rgb`` variants); the texture image is ``Non-Color``
  float data holding *linear* reflectance; frames are read back from a 32-bit
  OpenEXR file, i.e. linear radiance before any view transform ("Standard"
  is set anyway; no Filmic/AgX, no exposure, no denoiser).
- Light units agree by definition: a constant emitter's radiance is the
  world colour; a directional emitter's irradiance (W/m²) is a sun's
  strength; a point emitter's intensity I (W/sr) is a point light of power
  4π·I (W) with zero radius.
- Path length: Mitsuba's ``max_depth`` d counts the camera segment and
  emission, Cycles' bounces do not: ``max_bounces = d − 2``.
- Environment maps: Mitsuba's ``envmap`` looks a canonical direction d up at
  u = atan2(d.x, −d.z)/2π, v = acos(d.y)/π; Cycles' equirectangular
  Environment Texture a Blender direction b at u = 1/2 − atan2(b.y, b.x)/2π,
  v = 1/2 + asin(b.z)/π (v up). With b = C·d the two agree after turning b
  by 90° − θ about Blender's +Z (θ: ``envmap_rotation_deg``, Mitsuba's turn
  about +Y, the same turn about Blender's +Z); ``scale`` is the Background's
  strength.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from undream.scene.mesh import read_ply
from undream.scene.mitsuba_scene import OBJECT_ID, ScenePaths, scene_dict
from undream.spec import Frame, load_sequence

C4 = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
CAMERA_FLIP = np.diag([-1.0, 1.0, -1.0, 1.0])
SPHERE_SEGMENTS = (48, 24)  # analytic Mitsuba spheres as UV spheres (max radial error 0.2 %)


def _mat(node: dict[str, Any]) -> np.ndarray:
    return np.asarray(node["to_world"].m, dtype=float).reshape(4, 4)


def _mathutils_matrix(m: np.ndarray) -> Any:
    from mathutils import Matrix

    return Matrix([list(map(float, row)) for row in m])


def _rgb(node: dict[str, Any]) -> tuple[float, float, float]:
    return tuple(float(x) for x in node["value"])  # type: ignore[return-value]


# --- primitives in Mitsuba's local frames ------------------------------------------------------

def _uv_sphere(nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere at the origin (Mitsuba ``sphere``): vertices (N,3), triangles (T,3)."""
    verts = [(0.0, 0.0, 1.0)]
    for i in range(1, nv):
        th = math.pi * i / nv
        verts += [(math.sin(th) * math.cos(2 * math.pi * j / nu), math.sin(th) * math.sin(2 * math.pi * j / nu),
                   math.cos(th)) for j in range(nu)]
    verts.append((0.0, 0.0, -1.0))
    faces = [(0, 1 + j, 1 + (j + 1) % nu) for j in range(nu)]
    for i in range(nv - 2):
        a, b = 1 + i * nu, 1 + (i + 1) * nu
        for j in range(nu):
            k = (j + 1) % nu
            faces += [(a + j, b + j, b + k), (a + j, b + k, a + k)]
    last, base = len(verts) - 1, 1 + (nv - 2) * nu
    faces += [(base + j, last, base + (j + 1) % nu) for j in range(nu)]
    return np.array(verts), np.array(faces)


def _open_cylinder(n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's ``cylinder``: radius 1 around +Z from z = 0 to z = 1, no caps."""
    ang = 2 * math.pi * np.arange(n) / n
    ring = np.c_[np.cos(ang), np.sin(ang)]
    verts = np.r_[np.c_[ring, np.zeros(n)], np.c_[ring, np.ones(n)]]
    j, k = np.arange(n), (np.arange(n) + 1) % n
    faces = np.r_[np.c_[j, k, n + k], np.c_[j, n + k, n + j]]
    return verts, faces


def _cube() -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's ``cube``: [−1, 1]³."""
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def _rectangle() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mitsuba's ``rectangle``: [−1, 1]² at z = 0, normal +Z, uv = ((x + 1)/2, (y + 1)/2)."""
    v = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    return v, np.array([[0, 1, 2], [0, 2, 3]]), (v[:, :2] + 1) / 2


# --- Blender data ------------------------------------------------------------------------------

def _mesh(name: str, verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None = None,
          normals: np.ndarray | None = None, smooth: bool = False) -> Any:
    """A Blender mesh from vertices (N,3), triangles (T,3), per-vertex UVs (N,2) as Blender reads them."""
    me = bpy.data.meshes.new(name)
    me.from_pydata(np.asarray(verts, float).tolist(), [], np.asarray(faces, int).tolist())
    if uvs is not None:
        layer = me.uv_layers.new(name="UVMap")
        loops = np.zeros(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("vertex_index", loops)
        layer.data.foreach_set("uv", np.asarray(uvs, np.float32)[loops].ravel())
    if smooth or normals is not None:
        me.shade_smooth()
    if normals is not None:
        me.normals_split_custom_set_from_vertices(np.asarray(normals, float).tolist())
    me.update()
    return me


def _diffuse(name: str, colour: Any) -> Any:
    """A Lambertian material: ``colour`` an RGB (linear) or a node-building callable."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Roughness"].default_value = 0.0  # Lambert
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    if callable(colour):
        links.new(colour(nodes), bsdf.inputs["Color"])
    else:
        bsdf.inputs["Color"].default_value = (*colour, 1.0)
    return mat


def _object(name: str, mesh: Any, material: Any) -> Any:
    """A new object of ``mesh`` with its own ``material`` (meshes are shared: the sphere serves tree
    crowns of every colour and the fog volume, so the material is linked to the object, not the mesh)."""
    obj = bpy.data.objects.new(name, mesh)
    if not mesh.materials:
        mesh.materials.append(None)
    obj.material_slots[0].link = "OBJECT"
    obj.material_slots[0].material = material
    bpy.context.scene.collection.objects.link(obj)
    return obj


class CyclesScene:
    """The Blender scene of one scene directory, rendering any of its frames with Cycles on the CPU."""

    def __init__(self, scene_dir: str | Path, threads: int = 0):
        self.root = Path(scene_dir).resolve()
        self.seq = load_sequence(self.root / "sequence.json")
        self.frames: dict[int, Frame] = {f.index: f for f in self.seq.frames}
        self.paths = ScenePaths(str(self.root))
        self._tmp = tempfile.TemporaryDirectory(prefix="undream-cycles-")
        self._objects: dict[str, Any] = {}  # signature → Blender object
        self._meshes: dict[str, Any] = {}
        self._medium_nodes: tuple[Any, Any] | None = None
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self._setup_render(threads)
        self._setup_texture()
        self._setup_lights()

    # -- one-time setup ----------------------------------------------------------------------

    def _setup_render(self, threads: int) -> None:
        sc = self.scene
        sc.render.engine = "CYCLES"
        cy = sc.cycles
        cy.device = "CPU"
        cy.use_adaptive_sampling = False
        cy.use_denoising = False
        cy.use_light_tree = True
        cy.sample_clamp_direct = 0.0
        cy.sample_clamp_indirect = 0.0
        cy.pixel_filter_type = "GAUSSIAN"
        cy.filter_width = 1.5
        cy.caustics_reflective = cy.caustics_refractive = True
        sc.view_settings.view_transform = "Standard"
        sc.view_settings.look = "None"
        sc.view_settings.exposure = 0.0
        sc.view_settings.gamma = 1.0
        sc.render.film_transparent = False
        sc.render.resolution_percentage = 100
        sc.render.pixel_aspect_x = sc.render.pixel_aspect_y = 1.0
        # Persistent data would keep the first texture: Cycles does not re-sync an image whose pixels
        # changed (measured with bpy 5.0.1, even after update_tag), so every render syncs afresh.
        sc.render.use_persistent_data = False
        sc.render.threads_mode = "FIXED" if threads > 0 else "AUTO"
        if threads > 0:
            sc.render.threads = threads
        img = sc.render.image_settings
        img.file_format = "OPEN_EXR"
        img.color_depth = "32"
        img.exr_codec = "NONE"
        img.color_mode = "RGB"
        cam_data = bpy.data.cameras.new("camera")
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.sensor_width = 36.0
        cam_data.clip_start, cam_data.clip_end = 0.01, 1000.0
        self.camera = bpy.data.objects.new("camera", cam_data)
        sc.collection.objects.link(self.camera)
        sc.camera = self.camera
        sc.world = bpy.data.worlds.new("world")
        sc.world.use_nodes = True
        self.sky = sc.world.node_tree.nodes["Background"]
        self.sky.inputs["Strength"].default_value = 1.0
        self._setup_envmap_nodes()

    def _setup_envmap_nodes(self) -> None:
        """Generated (the view direction) → Mapping (a turn about +Z) → Environment Texture; linked to
        the Background only in frames with an envmap."""
        nodes = self.scene.world.node_tree.nodes
        coords = nodes.new("ShaderNodeTexCoord")
        self.env_mapping = nodes.new("ShaderNodeMapping")
        self.env_mapping.vector_type = "POINT"
        self.env_texture = nodes.new("ShaderNodeTexEnvironment")
        self.env_texture.projection = "EQUIRECTANGULAR"
        self.env_texture.interpolation = "Linear"
        links = self.scene.world.node_tree.links
        links.new(coords.outputs["Generated"], self.env_mapping.inputs["Vector"])
        links.new(self.env_mapping.outputs["Vector"], self.env_texture.inputs["Vector"])
        self._env_images: dict[str, Any] = {}

    def _setup_texture(self) -> None:
        tex = self.seq.texture
        w, h = tex.resolution
        self.texture_shape = tex.shape
        self.image = bpy.data.images.new("adv_texture", w, h, alpha=False, float_buffer=True)
        self.image.colorspace_settings.name = "Non-Color"
        self._rgba = np.ones((h, w, 4), dtype=np.float32)

        def texture_node(nodes: Any) -> Any:
            node = nodes.new("ShaderNodeTexImage")
            node.image = self.image
            node.interpolation = "Linear"
            node.extension = "REPEAT"
            return node.outputs["Color"]

        self.object_material = _diffuse("adv_material", texture_node)

    def _setup_lights(self) -> None:
        sun = bpy.data.lights.new("sun", "SUN")
        sun.angle = 0.0  # Mitsuba's directional emitter is a delta light
        lamp = bpy.data.lights.new("lamp", "POINT")
        lamp.shadow_soft_size = 0.0
        self.sun = bpy.data.objects.new("sun", sun)
        self.lamp = bpy.data.objects.new("lamp", lamp)
        for obj in (self.sun, self.lamp):
            self.scene.collection.objects.link(obj)

    # -- objects, built on first use and kept ------------------------------------------------

    def _ply_mesh(self, filename: str, uv_scale: tuple[float, float] | None) -> Any:
        key = f"{filename}|{uv_scale}"
        if key not in self._meshes:
            m = read_ply(filename)
            uvs = None
            if uv_scale is not None:
                su, sv = uv_scale
                uvs = np.c_[su * m.uvs[:, 0], 1.0 - sv * m.uvs[:, 1]]
            self._meshes[key] = _mesh(Path(filename).stem, m.vertices, m.faces, uvs, m.normals)
        return self._meshes[key]

    def _primitive(self, kind: str) -> Any:
        if kind not in self._meshes:
            if kind == "sphere":
                v, f = _uv_sphere(*SPHERE_SEGMENTS)
                self._meshes[kind] = _mesh(kind, v, f, normals=v)
            elif kind == "cylinder":
                v, f = _open_cylinder()
                self._meshes[kind] = _mesh(kind, v, f, normals=np.c_[v[:, :2], np.zeros(len(v))])
            elif kind == "cube":
                self._meshes[kind] = _mesh(kind, *_cube())
            else:
                v, f, uv = _rectangle()
                self._meshes[kind] = _mesh(kind, v, f, uvs=uv)
        return self._meshes[kind]

    def _material_of(self, key: str, node: dict[str, Any]) -> Any:
        if key == OBJECT_ID:
            return self.object_material
        bsdf = node.get("bsdf", {})
        if bsdf.get("type") == "twosided":
            bsdf = bsdf["bsdf"]
        refl = bsdf["reflectance"]
        if refl["type"] == "checkerboard":
            su, sv = refl["to_uv"].u, refl["to_uv"].v

            def checker(nodes: Any) -> Any:
                coords = nodes.new("ShaderNodeTexCoord")
                scale = nodes.new("ShaderNodeMapping")
                scale.inputs["Scale"].default_value = (2 * su, 2 * sv, 1.0)  # Mitsuba: 2×2 checks per uv unit
                chk = nodes.new("ShaderNodeTexChecker")
                chk.inputs["Scale"].default_value = 1.0
                # Cycles' Color1 where the checks' parities differ: Mitsuba's color1.
                chk.inputs["Color1"].default_value = (*_rgb(refl["color1"]), 1.0)
                chk.inputs["Color2"].default_value = (*_rgb(refl["color0"]), 1.0)
                nodes.id_data.links.new(coords.outputs["UV"], scale.inputs["Vector"])
                nodes.id_data.links.new(scale.outputs["Vector"], chk.inputs["Vector"])
                return chk.outputs["Color"]

            return _diffuse(f"{key}_material", checker)
        return _diffuse(f"{key}_material", _rgb(refl))

    def _fog_material(self, medium: dict[str, Any]) -> Any:
        """Homogeneous fog: scattering σ_s = albedo·σ_t, absorption (1 − albedo)·σ_t (1/m), isotropic."""
        mat = bpy.data.materials.new("fog")
        mat.use_nodes = True
        nodes, links = mat.node_tree.nodes, mat.node_tree.links
        nodes.clear()
        out = nodes.new("ShaderNodeOutputMaterial")
        scatter = nodes.new("ShaderNodeVolumeScatter")
        absorb = nodes.new("ShaderNodeVolumeAbsorption")
        add = nodes.new("ShaderNodeAddShader")
        scatter.inputs["Anisotropy"].default_value = 0.0
        scatter.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        absorb.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        links.new(scatter.outputs[0], add.inputs[0])
        links.new(absorb.outputs[0], add.inputs[1])
        links.new(add.outputs[0], out.inputs["Volume"])
        self._medium_nodes = (scatter, absorb)
        self._set_medium(medium)
        return mat

    def _set_medium(self, medium: dict[str, Any]) -> None:
        """The fog's densities for this frame (fog, rain and snow differ; one volume object serves all)."""
        assert self._medium_nodes is not None  # made by _fog_material before any frame uses it
        scatter, absorb = self._medium_nodes
        sigma_t = float(medium["sigma_t"]) * float(medium.get("scale", 1.0))
        albedo = float(np.mean(_rgb(medium["albedo"])))
        scatter.inputs["Density"].default_value = albedo * sigma_t
        absorb.inputs["Density"].default_value = (1.0 - albedo) * sigma_t

    def _signature(self, key: str, node: dict[str, Any]) -> str:
        if node["type"] == "ply":
            return f"{key}|{node['filename']}"
        if key == "fog_volume":
            return key
        return f"{key}|{node['type']}|{node.get('bsdf')!r}"

    def _get_object(self, key: str, node: dict[str, Any], d: dict[str, Any]) -> Any:
        sig = self._signature(key, node)
        if sig in self._objects:
            return self._objects[sig]
        if node["type"] == "ply":
            uv_scale = None
            if key == OBJECT_ID:
                to_uv = node["bsdf"]["bsdf"]["reflectance"]["to_uv"]
                uv_scale = (to_uv.u, to_uv.v)
            mesh = self._ply_mesh(node["filename"], uv_scale)
        else:
            mesh = self._primitive(node["type"])
        mat = self._fog_material(d["fog"]) if key == "fog_volume" else self._material_of(key, node)
        obj = _object(key, mesh, mat)
        if key == "fog_volume":
            obj.visible_shadow = True
        self._objects[sig] = obj
        return obj

    # -- a frame ---------------------------------------------------------------------------------

    def _shape_matrix(self, key: str, node: dict[str, Any]) -> np.ndarray:
        if node["type"] == "sphere" and "center" in node:
            m = np.diag([node["radius"]] * 3 + [1.0])
            m[:3, 3] = node["center"]
            return m
        return _mat(node)

    def _camera(self, sensor: dict[str, Any]) -> tuple[int, int, tuple[int, int, int, int]]:
        film = sensor["film"]
        fw, fh = int(film["width"]), int(film["height"])
        data = self.camera.data
        data.lens = data.sensor_width / (2.0 * math.tan(math.radians(sensor["fov"]) / 2.0))
        self.camera.matrix_world = _mathutils_matrix(C4 @ _mat(sensor) @ CAMERA_FLIP)
        ox, oy = int(film.get("crop_offset_x", 0)), int(film.get("crop_offset_y", 0))
        cw, ch = int(film.get("crop_width", fw)), int(film.get("crop_height", fh))
        return fw, fh, (ox, oy, cw, ch)

    def _world(self, sky: dict[str, Any] | None) -> None:
        """The world: a constant colour, or the frame's envmap (image loaded once per file)."""
        links = self.scene.world.node_tree.links
        colour_in = self.sky.inputs["Color"]
        for link in list(colour_in.links):
            links.remove(link)
        if sky is None or sky["type"] != "envmap":
            colour_in.default_value = (*_rgb(sky["radiance"]), 1.0) if sky else (0.0, 0.0, 0.0, 1.0)
            self.sky.inputs["Strength"].default_value = 1.0
            return
        path = str(Path(sky["filename"]).resolve())
        if path not in self._env_images:
            img = bpy.data.images.load(path, check_existing=False)
            img.colorspace_settings.name = "Non-Color"  # linear radiance as stored, no transform
            self._env_images[path] = img
        self.env_texture.image = self._env_images[path]
        # Cycles' automatic importance map is 1024 wide and rebuilt every render (no persistent data):
        # 2.3 s against 0.5 s per 64² frame of a 256-wide map; the map's own width samples it as well.
        world = self.scene.world.cycles
        world.sampling_method = "MANUAL"
        world.sample_map_resolution = int(min(max(self.env_texture.image.size[0], 32), 1024))
        m = _mat(sky)[:3, :3]
        theta = math.atan2(m[0, 2], m[0, 0])  # the envmap's turn about +Y (envmap_rotation)
        self.env_mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.pi / 2 - theta)
        self.sky.inputs["Strength"].default_value = float(sky.get("scale", 1.0))
        links.new(self.env_texture.outputs["Color"], colour_in)

    def _lights(self, d: dict[str, Any]) -> None:
        self._world(d.get("sky"))
        sun = d.get("sun")
        self.sun.hide_render = sun is None
        if sun is not None:
            irr = np.array(_rgb(sun["irradiance"]))
            strength = float(irr.max())
            self.sun.data.energy = strength
            self.sun.data.color = tuple(irr / strength) if strength > 0 else (1.0, 1.0, 1.0)
            travel = C4[:3, :3] @ np.asarray(sun["direction"], float)  # where the light goes
            from mathutils import Vector

            rot = Vector(tuple(travel)).to_track_quat("-Z", "Y").to_matrix().to_4x4()
            self.sun.matrix_world = rot
        lamp = d.get("lamp")
        self.lamp.hide_render = lamp is None
        if lamp is not None:
            inten = np.array(_rgb(lamp["intensity"]))
            peak = float(inten.max())
            self.lamp.data.energy = 4.0 * math.pi * peak
            self.lamp.data.color = tuple(inten / peak) if peak > 0 else (1.0, 1.0, 1.0)
            m = np.eye(4)
            m[:3, 3] = lamp["position"]
            self.lamp.matrix_world = _mathutils_matrix(C4 @ m)

    def _bounces(self, d: dict[str, Any]) -> None:
        cy = self.scene.cycles
        n = max(int(d["integrator"]["max_depth"]) - 2, 0)
        cy.max_bounces = cy.diffuse_bounces = cy.glossy_bounces = cy.transmission_bounces = n
        cy.volume_bounces = n
        cy.transparent_max_bounces = 16

    def set_frame(self, index: int) -> tuple[int, int, tuple[int, int, int, int]]:
        """Pose every object, light and the camera for frame ``index``; returns the film and crop."""
        if index not in self.frames:
            raise KeyError(f"frame index {index} is not in {self.root}/sequence.json "
                           f"(indices {min(self.frames)}..{max(self.frames)})")
        d = scene_dict(self.seq, self.frames[index], self.paths, "sim")
        shown = set()
        for key, node in d.items():
            if not isinstance(node, dict) or node.get("type") not in ("ply", "sphere", "cylinder", "cube",
                                                                       "rectangle"):
                continue
            obj = self._get_object(key, node, d)
            obj.matrix_world = _mathutils_matrix(C4 @ self._shape_matrix(key, node))
            obj.hide_render = False
            shown.add(obj.name)
        for obj in self._objects.values():
            if obj.name not in shown:
                obj.hide_render = True
        if "fog" in d:
            self._set_medium(d["fog"])
        self._lights(d)
        self._bounces(d)
        return self._camera(d["sensor"])

    def set_texture(self, texture_linear: np.ndarray) -> None:
        """Swap the adversarial texture: H×W×3 LINEAR reflectance (row 0 = Mitsuba's v = 0)."""
        tex = np.asarray(texture_linear, dtype=np.float32)
        if tex.shape != self.texture_shape:
            raise ValueError(f"texture has shape {tex.shape}, the scene's is {self.texture_shape} (H, W, 3)")
        self._rgba[..., :3] = tex[::-1]  # Blender images are stored bottom row first
        self.image.pixels.foreach_set(self._rgba.ravel())
        self.image.update()

    def _render_exr(self, film: tuple[int, int, tuple[int, int, int, int]], spp: int, seed: int) -> np.ndarray:
        """Render the posed frame; H×W×4 linear RGBA of the camera's crop window."""
        fw, fh, (ox, oy, cw, ch) = film
        sc = self.scene
        sc.render.resolution_x, sc.render.resolution_y = fw, fh
        sc.cycles.samples = int(spp)
        sc.cycles.seed = int(seed)
        path = Path(self._tmp.name) / "frame.exr"
        sc.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(str(path), check_existing=False)
        try:
            px = np.empty(fw * fh * img.channels, dtype=np.float32)
            img.pixels.foreach_get(px)
            rgba = px.reshape(fh, fw, img.channels)[::-1]
        finally:
            bpy.data.images.remove(img)
        if rgba.shape[2] == 3:
            rgba = np.concatenate([rgba, np.ones_like(rgba[..., :1])], axis=2)
        return np.ascontiguousarray(rgba[oy:oy + ch, ox:ox + cw])

    def render(self, index: int, texture_linear: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """Frame ``index`` with ``texture_linear`` at ``spp`` samples and ``seed``: H×W×3 linear radiance."""
        self.set_texture(texture_linear)
        return self._render_exr(self.set_frame(index), spp, seed)[..., :3].copy()

    def coverage(self, index: int, spp: int) -> np.ndarray:
        """The object's visible coverage in frame ``index`` (H×W in [0, 1], box filter).

        Every other surface is a holdout (occludes, adds no alpha), the world
        and the fog are transparent: the film's alpha is what the object covers,
        as Mitsuba's mask scene measures it.
        """
        film = self.set_frame(index)
        sc, cy = self.scene, self.scene.cycles
        saved = (sc.render.film_transparent, cy.pixel_filter_type, cy.filter_width,
                 sc.render.image_settings.color_mode)
        changed = []
        for sig, o in self._objects.items():
            key = sig.split("|", 1)[0]  # Blender renames a second "object" (per-frame meshes) "object.001"
            if o.hide_render:
                continue
            if key == "fog_volume":
                o.hide_render = True
                changed.append((o, "hide_render", False))
            elif key != OBJECT_ID:
                o.is_holdout = True
                changed.append((o, "is_holdout", False))
        sc.render.film_transparent = True
        cy.pixel_filter_type, cy.filter_width = "BOX", 1.0
        sc.render.image_settings.color_mode = "RGBA"
        try:
            alpha = self._render_exr(film, spp, 0)[..., 3].copy()
        finally:
            for o, attr, value in changed:
                setattr(o, attr, value)
            (sc.render.film_transparent, cy.pixel_filter_type, cy.filter_width,
             sc.render.image_settings.color_mode) = saved
        return alpha

    def threads(self) -> int:
        """The CPU threads Cycles renders with (fixed, or Blender's count of all cores)."""
        return int(self.scene.render.threads)

    def versions(self) -> dict[str, str]:
        return {"blender": bpy.app.version_string, "cycles_device": "CPU", "numpy_blender": np.__version__}
