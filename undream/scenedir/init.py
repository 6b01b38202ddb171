"""``undream init``: a scene directory from a trajectory spec, an Unreal export, a sequence.json or a .blend.

Layout written (atomically: into a temporary sibling, renamed at the end)::

    sequence.json            canonical sequence
    metadata.json            spec, seed, versions, verification settings
    meshes/object.ply        the adversarial mesh (canonical, metres, UV-mapped)
    meshes/<actor>.ply       one per extra actor
    meshes/<id>_NNNN.ply     instead, frame NNNN's mesh of a per-frame mesh (``{frame}`` in its path)
    textures/<name>.exr      initial texture, LINEAR float (what the scenes load, raw)
    textures/<name>.png      the same, sRGB 8-bit (what a person looks at)
    frames/sim_NNNN.xml      the whole scene of frame NNNN
    frames/grad_NNNN.xml     the object's appearance only, for prb
    verify/white_NNNN.png    the simulation scene with a white texture (sRGB)
    verify/mask_NNNN.png     the object's visible pixels (255) in that frame
    verify/contact_sheet.png every white render with its mask outlined
"""
from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from undream import __version__
from undream.bridge.blender_import import BlendSource
from undream.color import linear_to_srgb, srgb_to_linear, to_uint8
from undream.errors import AssetError, SpecError, already_exists
from undream.progress import progress
from undream.render.budget import Estimate, init_estimate
from undream.scene.builtin import asset_mesh
from undream.scene.layout import frame_name, frame_xml, mask_png, mesh_name
from undream.scene.mesh import Mesh, write_ply
from undream.scene.mitsuba_scene import OBJECT_ID, ScenePaths, scene_dict, with_haze
from undream.scene.texture_file import read_image_rgb
from undream.scene.sources import sequence_from_file
from undream.scene.xml import to_xml
from undream.scenedir.envmaps import Envmap, envmap_sources, load_envmaps, write_envmaps
from undream.scenedir.verify import check_seen, contact_sheet, render_frames, save_mask, save_rgb
from undream.spec import Sequence, TextureParam, save_sequence
from undream.spec.io import check_writable_target, join_against, naming, resolve_against
from undream.variant import mitsuba
from undream.versions import versions

Source = str | Path | Sequence | BlendSource  # a spec file, a sequence, or a .blend and its object


@dataclass(frozen=True)
class InitOptions:
    """How ``undream init`` writes a scene directory."""

    force: bool = False  # replace an existing directory
    verify_spp: int = 16  # samples per pixel of the verification renders
    scene_spp: int = 64  # the default ``$spp`` written into the XML files
    progress: bool = False  # show a progress bar
    memory_limit: int | None = None  # bytes the renders may use (None: MemAvailable; the edge reads $UNDREAM_MEMORY_LIMIT)
    frozen: bool = True  # the verification renders as Dr.Jit frozen functions (the edge reads $UNDREAM_FROZEN)
    cache_dir: str | None = None  # undream's cache folder, where a spec's asset:NAME is (<cache_home>/undream)


@dataclass(frozen=True)
class CheckedSource:
    """A spec that passed every check ``undream init`` makes before it writes: what it would write from."""

    sequence: Sequence
    base_dir: Path | None  # relative mesh and texture paths resolve against it (the spec's folder)
    spec_text: str | None
    meshes: dict[str, object]  # file stem in meshes/ → mesh (OBJECT_ID, actor names, NAME_NNNN per frame)
    texture: np.ndarray  # the starting texture, H×W×3 sRGB in [0, 1]
    estimate: Estimate  # memory and samples of the verification renders
    envmaps: tuple[Envmap, ...] = ()  # environment maps, as the scene directory holds them


def check_source(source: Source, options: InitOptions = InitOptions(),
                 spec_text: str | None = None) -> CheckedSource:
    """Everything ``undream init`` checks before it writes: the spec parsed, meshes (with UVs)
    and the texture loaded, the verification renders' memory checked. Writes nothing.

    Mesh and texture paths may point anywhere (relative ones resolve against
    the spec's folder, ``..`` included): their content is copied into the
    scene directory, which never refers to a file outside itself, and
    ``metadata.json`` records where each mesh came from. Environment maps
    likewise: copied to ``textures/envmap*.exr``, which the written
    ``sequence.json`` names (:mod:`undream.scenedir.envmaps`).
    """
    seq, base_dir, spec_text = _resolve_source(source, spec_text, options.cache_dir)
    try:
        meshes = _load_meshes(seq, base_dir)
        texture = texture_from_spec(seq.texture, base_dir)
        seq, envmaps = load_envmaps(seq, base_dir)
    except AssetError as err:
        raise AssetError(f"{source}: {err}" if not isinstance(source, Sequence) else str(err)) from None
    try:
        estimate = init_estimate(seq, options.verify_spp, limit=options.memory_limit)
    except SpecError as err:
        raise SpecError(f"{source}: {err}" if not isinstance(source, Sequence) else str(err)) from None
    return CheckedSource(seq, base_dir, spec_text, meshes, texture, estimate, tuple(envmaps))


def init_scene(source: Source, out: str | Path, options: InitOptions = InitOptions(),
               spec_text: str | None = None) -> Path:
    """Write the scene directory of ``source`` to ``out`` and return its path.

    ``source`` is a spec file (YAML trajectory, Unreal export JSON, canonical
    sequence.json), a :class:`Sequence` or a :class:`BlendSource`. Everything is checked first
    (:func:`check_source`); nothing is left behind on error, and an existing
    ``out`` is only replaced with ``options.force``.
    """
    out = Path(out)
    _check_target(out, options.force)
    checked = check_source(source, options, spec_text)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{time.monotonic_ns()}"
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        _write(checked, tmp, options)
        try:
            check_seen(tmp, checked.sequence)  # every condition's frames show the object
        except SpecError as err:
            raise SpecError(f"{source}: {err}" if not isinstance(source, Sequence) else str(err)) from None
        _check_target(out, options.force)
        _swap_into_place(tmp, out)
    except OSError as err:  # a full disk: the file that could not be written, as the scene would hold it
        shutil.rmtree(tmp, ignore_errors=True)
        if err.filename is None or not Path(err.filename).is_relative_to(tmp):
            raise
        raise OSError(err.errno, err.strerror, str(out / Path(err.filename).relative_to(tmp))) from err
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def check_init(source: Source, out: str | Path, options: InitOptions = InitOptions()) -> Estimate:
    """``undream init --check``: every check of :func:`init_scene`, nothing written; the estimate."""
    _check_target(Path(out), options.force)
    return check_source(source, options).estimate


def _check_target(out: Path, force: bool) -> None:
    if out.exists() and not force:
        raise already_exists(out)
    check_writable_target(out.parent if out.is_dir() else out)


def _resolve_source(source: Source, spec_text: str | None,
                    cache_dir: str | None) -> tuple[Sequence, Path | None, str | None]:
    if isinstance(source, Sequence):
        return source, None, spec_text
    if isinstance(source, BlendSource):
        return sequence_from_file(source), Path(source.path).parent, source.describe()

    path = Path(source)
    seq = sequence_from_file(path, cache_dir)
    return seq, path.parent, path.read_text()


def _load_meshes(seq: Sequence, base_dir: Path | None) -> dict[str, object]:
    """Mesh file stem in ``meshes/`` → mesh: ``object``, each actor's name, or ``NAME_NNNN`` per frame.

    A per-frame mesh needs a file for every frame that shows it; the
    adversarial object's must all share the first one's triangles and UVs
    (one UV layout, so a texel stays on the same piece of surface).
    """
    out: dict[str, object] = {}
    shown = {a.name: [f.index for f in seq.frames if any(p.name == a.name for p in f.actors)] for a in seq.actors}
    for field, asset in [("asset", seq.asset)] + [(f"actors[{i}]", a) for i, a in enumerate(seq.actors)]:
        key = OBJECT_ID if field == "asset" else asset.name
        try:
            if not asset.per_frame:
                out[key] = asset_mesh(asset, base_dir)
                continue
            loaded: dict[str, Mesh] = {}  # one load per distinct file
            for index in ([f.index for f in seq.frames] if field == "asset" else shown[asset.name]):
                file = asset.mesh_at(index)
                if file not in loaded:
                    loaded[file] = asset_mesh(asset, base_dir, index)
                out[mesh_name(key, index)] = loaded[file]
                if field == "asset":
                    _same_uv_layout(loaded[file], out[mesh_name(key, seq.frames[0].index)], file, index)
        except AssetError as err:
            raise AssetError(f"{field}.mesh ({asset.name!r}): {err}") from None
    return out


def _same_uv_layout(mesh: Mesh, first: Mesh, file: str, index: int) -> None:
    if mesh is first:
        return
    if mesh.n_vertices != first.n_vertices or not np.array_equal(mesh.faces, first.faces) \
            or not np.allclose(mesh.uvs, first.uvs, atol=1e-6):
        raise AssetError(f"{file} (frame {index}) has another UV layout than the first frame's "
                         f"({mesh.n_vertices} vertices, {mesh.n_faces} triangles against {first.n_vertices}, "
                         f"{first.n_faces}, or other UVs); the adversarial object's per-frame meshes may move "
                         "their vertices but must keep their triangles and UVs")


def texture_from_spec(tex: TextureParam, base_dir: Path | None) -> np.ndarray:
    """The starting texture of ``tex``: H×W×3 float32 sRGB in [0, 1] (``tex.shape``).

    A colour fills it; an image file (relative to ``base_dir``) is resized to
    ``tex.resolution`` (width, height), bilinearly.
    """
    if not isinstance(tex.init, str):
        return np.broadcast_to(np.array(tex.init, np.float32), tex.shape).copy()
    path = join_against(tex.init, base_dir)
    try:  # its size checked before it is decoded, 16-bit greyscale scaled (read_image_rgb)
        img = read_image_rgb(path, str(path)).resize(tex.resolution, Image.BILINEAR)
    except SpecError as err:
        raise AssetError(f"{err} (asset.texture.init)") from None
    return np.asarray(img, dtype=np.float32) / 255.0


def _write(checked: CheckedSource, root: Path, opt: InitOptions) -> None:
    seq, meshes, texture = checked.sequence, checked.meshes, checked.texture
    mi = mitsuba()
    for sub in ("meshes", "textures", "frames", "verify"):
        (root / sub).mkdir(parents=True)
    save_sequence(seq, root / "sequence.json")
    for name, mesh in meshes.items():
        write_ply(mesh, root / "meshes" / f"{name}.ply")
    tex = seq.texture
    with naming(root / "textures" / f"{tex.name}.exr"):
        mi.Bitmap(srgb_to_linear(texture)).write(str(root / "textures" / f"{tex.name}.exr"))
    with naming(root / "textures" / f"{tex.name}.png"):
        Image.fromarray(to_uint8(texture)).save(root / "textures" / f"{tex.name}.png")
    write_envmaps(list(checked.envmaps), root)
    rel = ScenePaths("..")
    defaults = {"spp": opt.scene_spp}
    for frame in seq.frames:  # the mask scenes only while the frames are verified
        for kind in ("sim", "grad", "mask"):
            with naming(frame_xml(root, kind, frame.index)):
                d = with_haze(scene_dict(seq, frame, rel, kind))
                frame_xml(root, kind, frame.index).write_text(to_xml(d, defaults))
    tiles = []
    indices = [frame.index for frame in seq.frames]
    renders = render_frames(mi, root, indices, opt.verify_spp, opt.frozen)
    for index, white, mask in progress(renders, "init frames", "frame", opt.progress, total=len(indices)):
        save_rgb(white, root / "verify" / f"{frame_name('white', index)}.png")
        save_mask(mask, mask_png(root, index))
        tiles.append((f"frame {index}", to_uint8(linear_to_srgb(white)), mask))
    for index in indices:
        frame_xml(root, "mask", index).unlink()
    contact_sheet(tiles, root / "verify" / "contact_sheet.png")
    _write_metadata(checked, root, opt, mi)


def _mesh_sources(seq: Sequence, base_dir: Path | None) -> dict[str, str]:
    """Where each mesh came from: ``builtin:NAME`` or the file's absolute path."""
    out = {}
    for key, asset in [(OBJECT_ID, seq.asset)] + [(a.name, a) for a in seq.actors]:
        # a per-frame mesh: its pattern ({frame}), resolved
        out[key] = asset.mesh if asset.builtin is not None else resolve_against(asset.mesh, base_dir)
    return out


def _write_metadata(checked: CheckedSource, root: Path, opt: InitOptions, mi) -> None:
    seq, spec_text = checked.sequence, checked.spec_text
    meta = {
        "undream": __version__, "created_unix": time.time(), "seed": seq.seed, "source": seq.source,
        "spec": spec_text, "frames": len(seq.frames), "object_id": OBJECT_ID,
        "mesh_sources": _mesh_sources(seq, checked.base_dir),
        "envmap_sources": envmap_sources(list(checked.envmaps)),
        "texture": {"name": seq.texture.name, "file": f"textures/{seq.texture.name}.exr",
                    "space": "linear (raw)", "srgb_preview": f"textures/{seq.texture.name}.png"},
        "verify_spp": opt.verify_spp, "scene_spp": opt.scene_spp, "variant": mi.variant(),
        "versions": versions(mi),
    }
    with naming(root / "metadata.json"):
        (root / "metadata.json").write_text(json.dumps(meta, indent=1) + "\n")


def _swap_into_place(tmp: Path, out: Path) -> None:
    if out.exists():
        trash = out.parent / f".{out.name}.old-{os.getpid()}-{time.monotonic_ns()}"
        out.rename(trash)
        tmp.rename(out)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        tmp.rename(out)
