"""``undream export SOURCE --out DIR --dpi N``: a texture as files to print (docs/printing.md).

SOURCE is an ``undream run`` output folder (its ``texture_final.npy``, the scene its
``metadata.json`` names, its config's ``gamut``) or a texture file (PNG or .npy, sRGB) with
``--scene``. DIR receives ``texture_print.png`` (sRGB, profile and DPI embedded),
``texture_print.pdf`` (one page of the print's size; the printer's CMYK with its profile, or
sRGB), ``preview.png`` (the object wearing the texture, a few of the scene's frames rendered by
Mitsuba) and ``export.json`` (sizes, DPI, profile, source). Everything is checked before DIR is
written; bad input is one line on stderr, exit 2.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import click
import numpy as np
from PIL import Image

from undream.cli.errors import one_line_errors
from undream.cli.options import force_option, local_settings, out_option, progress_option, spp_option
from undream.errors import SpecError

OUTPUTS = ("texture_print.png", "texture_print.pdf", "preview.png", "export.json")


def _read_texture(path: Path) -> np.ndarray:
    """An sRGB texture file as H×W×3 float32 in [0, 1]: .npy (floats in [0, 1]) or an image (8-bit)."""
    if not path.is_file():
        raise SpecError(f"texture: {path}: no such file")
    try:
        if path.suffix.lower() == ".npy":
            data = np.load(path, allow_pickle=False)
        else:
            with Image.open(path) as im:
                data = np.asarray(im.convert("RGB")).astype(np.float32) / 255.0
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise SpecError(f"texture: {path}: cannot be read ({' '.join(str(err).split())})") from None
    if data.ndim != 3 or data.shape[2] != 3 or not np.issubdtype(data.dtype, np.floating) \
            or not np.isfinite(data).all() or data.min() < 0 or data.max() > 1:
        raise SpecError(f"texture: {path}: must be sRGB H×W×3 in [0, 1], got shape {data.shape}, dtype {data.dtype}")
    return data.astype(np.float32)


def _source(source: Path, scene: Path | None) -> tuple[np.ndarray, Path, str]:
    """(texture, scene directory, the run's gamut or none) of SOURCE."""
    if source.is_dir():
        try:
            meta = json.loads((source / "metadata.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            raise SpecError(f"SOURCE {source}: not an output folder of `undream run` (no readable "
                            "metadata.json); give the folder a run wrote, or a texture file with --scene") from None
        texture = source / "texture_final.npy"
        if not texture.is_file():
            raise SpecError(f"SOURCE {source}: holds no texture_final.npy (has the run finished?)")
        scene_dir = scene or Path(str(meta.get("scene_dir") or ""))
        gamut = str((meta.get("config") or {}).get("gamut") or "none")
        return _read_texture(texture), scene_dir, gamut
    if not source.exists():
        raise SpecError(f"SOURCE {source}: no such run folder or texture file")
    if scene is None:
        raise SpecError(f"SOURCE {source}: a texture file needs --scene (the scene directory of the object it is for)")
    return _read_texture(source), scene, "none"


def _scene(scene_dir: Path, texture: np.ndarray) -> tuple[Any, Any]:
    """(sequence, mesh) of a scene directory, the texture's size checked against the scene's."""
    from undream.scene.mesh import read_ply
    from undream.spec import load_sequence

    if not (scene_dir / "sequence.json").is_file():
        raise SpecError(f"--scene: {scene_dir} is not a scene directory (no sequence.json); give the run's "
                        "scene directory with --scene")
    seq = load_sequence(scene_dir / "sequence.json")
    want = tuple(seq.asset.texture.resolution)
    if texture.shape[1::-1] != want:
        raise SpecError(f"texture: {texture.shape[1]}×{texture.shape[0]} texels, but the scene's texture is "
                        f"{want[0]}×{want[1]}")
    return seq, read_ply(scene_dir / "meshes" / "object.ply")


def _object_scale(seq: Any) -> float:
    """The object's uniform scale in the first frame (the cube root of its transform's determinant)."""
    m = np.asarray(seq.frames[0].object_to_world.matrix, np.float64)[:3, :3]
    return float(abs(np.linalg.det(m)) ** (1 / 3))


def _preview(scene_dir: Path, seq: Any, texture: np.ndarray, frames: int, spp: int, bar: Any) -> np.ndarray:
    """Up to ``frames`` of the scene's frames (evenly spread) with ``texture``, side by side (8-bit sRGB)."""
    from undream.color import linear_to_srgb, to_uint8
    from undream.render.scene_cache import SceneCache
    from undream.sim import make_backend

    scenes = SceneCache(scene_dir)
    sim = make_backend("mitsuba", scene_dir, scenes=scenes)
    picks = sorted({int(i) for i in np.linspace(0, len(seq.frames) - 1, min(frames, len(seq.frames)))})
    images = []
    for i in picks:
        images.append(to_uint8(linear_to_srgb(sim.render(seq.frames[i].index, texture, spp, 0))))
        bar.update(1)
    height = max(im.shape[0] for im in images)
    padded = [np.pad(im, ((0, height - im.shape[0]), (0, 0), (0, 0)), constant_values=255) for im in images]
    return np.concatenate(padded, axis=1)


@click.command("export")
@click.argument("source", type=click.Path(path_type=Path))
@out_option("Folder to write: texture_print.png, texture_print.pdf, preview.png, export.json.")
@click.option("--dpi", type=float, default=300.0, show_default=True, help="Dots per inch of the print.")
@click.option("--width-cm", type=float, default=None,
              help="Print this wide (the height keeps the aspect); default: the texture's real size on the mesh.")
@click.option("--scene", type=click.Path(path_type=Path), default=None,
              help="The scene directory (default: the run's; required for a texture file).")
@click.option("--profile", default=None, metavar="default|none|PATH.icc",
              help="The printer's CMYK profile (default: the run's gamut; none for a texture file).")
@click.option("--resample", type=click.Choice(["bilinear", "nearest"]), default="bilinear", show_default=True,
              help="Texels to print pixels: bilinear (as the renderer samples them) or nearest (blocks).")
@click.option("--preview-frames", type=click.IntRange(0, 16), default=4, show_default=True,
              help="Frames of the scene in preview.png (0: no preview).")
@spp_option("--preview-spp", 32, "Samples per pixel of the preview renders.")
@force_option
@progress_option
@one_line_errors
def export_cmd(source: Path, out: Path, dpi: float, width_cm: float | None, scene: Path | None, profile: str | None,
               resample: str, preview_frames: int, preview_spp: int, force: bool, progress: bool) -> None:
    """Write SOURCE's texture for print: an `undream run` output folder, or a texture file with --scene."""
    from scheduler.preflight import check_output_folder
    from undream.printing.export import describe, print_pixels, print_size, write_pdf, write_png
    from undream.printing.gamut import load_gamut
    from undream.printing.profiles import resolve_gamut
    from undream.printing.size import texel_size
    from undream.progress import progress as progress_bar

    local = local_settings(render=preview_frames > 0)
    texture, scene_dir, run_gamut = _source(source, scene)
    seq, mesh = _scene(scene_dir, texture)
    icc = resolve_gamut(run_gamut if profile is None else profile, local.undream_cache, "--profile")
    texel = texel_size(mesh.vertices, mesh.faces, mesh.uvs, texture.shape[1::-1], seq.asset.texture.uv_scale,
                       _object_scale(seq))
    size = print_size(texel, texture.shape[1::-1], dpi, width_cm)
    check_output_folder(out, scene_dir, force, command="undream export", marker=OUTPUTS[3], inputs=(source, icc))
    if out.exists() and any(out.iterdir()):  # an earlier export, and --force (checked just above)
        shutil.rmtree(out)
    bar = progress_bar(3 + preview_frames, "export", "step", progress)
    try:
        gamut = None if icc is None else load_gamut(icc)
        bar.update(1)
        pixels = print_pixels(texture, size, resample, gamut)
        out.mkdir(parents=True, exist_ok=True)
        write_png(out / OUTPUTS[0], pixels, size.dpi)
        bar.update(1)
        write_pdf(out / OUTPUTS[1], pixels, size, icc)
        bar.update(1)
        if preview_frames:
            shown = texture if gamut is None else gamut.project(texture)
            Image.fromarray(_preview(scene_dir, seq, shown, preview_frames, preview_spp, bar)).save(out / OUTPUTS[2])
    finally:
        bar.close()
    record = {"source": str(source.resolve()), "scene_dir": str(scene_dir.resolve()), "resample": resample,
              **describe(size, texel, icc, None if gamut is None else gamut.name)}
    (out / OUTPUTS[3]).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    click.echo(f"wrote {out}: {size.width_m * 100:.1f} × {size.height_m * 100:.1f} cm at {size.dpi:g} DPI "
               f"({size.pixels[0]} × {size.pixels[1]} px; real size {texel.width_m * 100:.1f} × "
               f"{texel.height_m * 100:.1f} cm, {texel.metres * 1000:.2f} mm a texel), "
               f"{'CMYK ' + (gamut.name if gamut else '') if icc else 'sRGB'}")


COMMANDS = (export_cmd,)
