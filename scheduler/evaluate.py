"""``undream evaluate``: judge a texture on scenes, victims and simulators it was never optimised for.

The texture is worn by the object of each scene (8-bit, as a user would print
or import it), every frame is rendered at ``spp`` by the chosen simulator,
and each victim judges the frames: on every frame, and apart on the frames
a run with ``holdout`` would attack and hold out. The scene's own texture is
judged the same way (``benign``), so each row says how much the texture
moved the victim. It is the function the runs' evaluation and the baseline
use (:func:`undream.engine.patch.evaluate_texture`). Everything is checked
(the texture file, its size against each scene's texture, the victims)
before anything renders.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from scheduler.preflight import is_scene
from scheduler.scenes import unpack_scene
from undream.engine.job import prediction_record, top_detections, truth_box
from undream.errors import SpecError, StoreError
from undream.scene.mesh import Mesh, read_ply
from undream.scene.texture_file import read_image_rgb, read_npy_texture
from undream.scene.mitsuba_scene import OBJECT_ID
from undream.scenedir.init import InitOptions, init_scene
from undream.settings import LocalSettings
from undream.spec.io import load_sequence
from undream.spec.run import TASK_LOSSES, RunConfig, split_conditions

if TYPE_CHECKING:
    from undream.store import Store

TEXTURE_FILE = "texture_final.npy"  # what `undream run` leaves in its output folder


def run_scene(path: Path) -> Path | None:
    """The scene directory an ``undream run`` output folder was optimised on (its ``metadata.json``'s
    ``scene_dir``), when ``path`` is one and that scene is still there; else None."""
    try:
        scene = Path(json.loads((path / "metadata.json").read_text())["scene_dir"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return scene if is_scene(scene) else None


def _object_mesh(scene_dir: Path) -> Mesh:
    """The adversarial object's mesh of a scene directory (its first frame's, if per frame)."""
    files = sorted((scene_dir / "meshes").glob(f"{OBJECT_ID}*.ply"))
    if not files:
        raise SpecError(f"SCENE {scene_dir}: no {OBJECT_ID} mesh in its meshes/")
    return read_ply(files[0])


def check_uv_layout(reference: Path, scene_dir: Path, scene: Path) -> None:
    """SpecError naming ``scene`` when its object's triangles or UVs, or its texture's resolution or
    ``uv_scale`` (how often the texture repeats over the UVs), differ from those of the scene the
    texture was optimised on (``reference``): a texel would land elsewhere on the surface."""
    ref_tex, got_tex = (load_sequence(d / "sequence.json").texture for d in (reference, scene_dir))
    if (got_tex.resolution, got_tex.uv_scale) != (ref_tex.resolution, ref_tex.uv_scale):
        raise SpecError(f"SCENE {scene}: its texture is {_texture_size(got_tex)}, the scene the texture was "
                        f"optimised on ({reference}) has {_texture_size(ref_tex)}: its texels would land elsewhere")
    ref, got = _object_mesh(reference), _object_mesh(scene_dir)
    if got.n_vertices != ref.n_vertices or not np.array_equal(got.faces, ref.faces) \
            or not np.allclose(got.uvs, ref.uvs, atol=1e-6):
        raise SpecError(f"SCENE {scene}: its object has another UV layout than the scene the texture was "
                        f"optimised on ({got.n_vertices} vertices, {got.n_faces} triangles against "
                        f"{ref.n_vertices}, {ref.n_faces}, or other UVs): its texels would land elsewhere")


def _texture_size(tex: Any) -> str:
    return f"{tex.resolution[0]}×{tex.resolution[1]} texels at uv_scale {tex.uv_scale[0]:g}×{tex.uv_scale[1]:g}"


def read_texture(path: Path) -> np.ndarray:
    """An H×W×3 sRGB texture in [0, 1] from a ``.npy`` (float in [0, 1], or uint8), a ``.png``, or an
    ``undream run`` output folder (its ``texture_final.npy``); SpecError naming the file otherwise."""
    if path.is_dir():
        if not (path / TEXTURE_FILE).is_file():
            raise SpecError(f"TEXTURE {path}: a folder without {TEXTURE_FILE} (not an `undream run` output folder)")
        path = path / TEXTURE_FILE
    if not path.is_file():
        raise SpecError(f"TEXTURE {path}: no such file")
    name = f"TEXTURE {path}"
    if path.suffix.lower() == ".npy":  # header, shape and size checked before the data is read
        array = read_npy_texture(path, name)
    elif path.suffix.lower() == ".png":  # its size checked before it is decoded; 16-bit scaled
        array = np.asarray(read_image_rgb(path, name))
    else:
        raise SpecError(f"{name}: give a .npy, a .png or an `undream run` output folder")
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if not np.issubdtype(array.dtype, np.floating) or not np.isfinite(array).all() \
            or array.min() < 0 or array.max() > 1:
        raise SpecError(f"{name}: values must be uint8, or finite floats in [0, 1] (this one is {array.dtype})")
    return array.astype(np.float32)


def _scene_dir(scene: Path, work: Path, local: LocalSettings) -> Path:
    """A scene directory as given, or a spec file initialised into ``work``."""
    if is_scene(scene):
        return scene
    if not scene.is_file():
        raise SpecError(f"SCENE {scene}: neither a scene directory nor a spec file")
    return init_scene(scene, work / f"scene-{len(list(work.iterdir()))}",
                      InitOptions(force=True, memory_limit=local.memory_limit, frozen=local.frozen,
                                  cache_dir=local.undream_cache))


Texture = tuple[np.ndarray, "Path | None"]  # the texture and the scene directory it was optimised on, if known


def texture_name(run: Any) -> str:
    """How :func:`farm_textures` names a farm run's final texture: ``name (id8)``."""
    return f"{run.name} ({run.id[:8]})"


def run_victim(path: Path) -> str | None:
    """The victim an ``undream run`` output folder's texture was attacked against (its
    ``metadata.json``'s config), when ``path`` is one that says; else None."""
    try:
        victim = json.loads((path / "metadata.json").read_text())["config"]["victim"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return victim if isinstance(victim, str) and victim else None


def farm_textures(store: "Store", ref: str, cache_dir: Path | str,
                  victims: list[str] | None = None) -> dict[str, Texture]:
    """The final textures of the farm's run ``ref`` (an id or its first characters), else of every
    run of sweep ``ref`` (an id or a name) that has one, by ``name (id8)``, each with its run's scene
    (unpacked under ``cache_dir``) for the UV-layout check; SpecError in one line when there is none.
    ``victims``, when given, receives the victims those runs attacked, each once, in run order."""
    try:
        runs, what = [store.find_run(ref)], "run"
    except StoreError as run_err:
        try:
            sweep = store.find_sweep(ref)
        except StoreError:
            raise SpecError(f"TEXTURE {ref}: no such file, and no run or sweep by that id or name in the farm "
                            f"({run_err})") from None
        runs, what = store.runs_page(sweep_id=sweep.id, limit=None, newest_first=False).runs, f"sweep {sweep.name}"
    out = {}
    for run in runs:
        final = store.final_texture(run.id)
        if final is None:
            continue
        scene = unpack_scene(store.blobs, run.scene_ref, cache_dir) if run.scene_ref else None
        out[texture_name(run)] = (final, scene)
        if victims is not None and run.run_config.victim not in victims:
            victims.append(run.run_config.victim)
    if not out:
        raise SpecError(f"TEXTURE {ref}: the {what} has no final texture yet (a run has one once its evaluation "
                        "picked it)")
    return out


def frame_rows(ctx: Any, parts: Any, benign: Sequence[Any], texture: Sequence[Any]) -> list[dict[str, Any]]:
    """One row per frame of ``ctx``'s sequence: its index, condition (a multi-condition scene's, else
    empty), split (``attacked`` or ``held_out``, as :func:`split_conditions` made ``parts``) and the
    victim's verdict on it with the scene's own texture (``benign_*``) and with the texture
    (``texture_*``): a classifier's predicted class, its probability and whether it is the object's;
    a detector's whether it found the object, its top score and its number of detections, the top
    detection's ``top_box`` (``[x0, y0, x1, y1]``, frame pixels) and ``top_label`` (class name; None
    without detections) and ``boxes`` (:func:`undream.engine.job.top_detections`: at most the five
    highest-scoring), and the frame's ``truth_box`` (the object's mask box, x1/y1 exclusive; None
    where it is unseen)."""
    conditions = {p: part.name for part, span in ctx.sequence.condition_ranges() for p in span} \
        if ctx.sequence.conditions else {}
    held = set(parts.held)
    detector = ctx.victim.task != "classification"
    rows = []
    for p in range(len(ctx.sequence.frames)):
        row: dict[str, Any] = {"frame": ctx.frame_indices[p], "condition": conditions.get(p, ""),
                               "split": "held_out" if p in held else "attacked"}
        if detector:
            row["truth_box"] = truth_box(ctx.targets[p])
        for prefix, preds in (("benign", benign), ("texture", texture)):
            record = prediction_record(ctx, p, preds[p])
            if "label" in record:
                record["label"] = ctx.victim.labels[record["label"]]
            if detector:
                boxes = top_detections(preds[p], ctx.victim.labels)
                record.update(top_box=boxes[0]["box"] if boxes else None,
                              top_label=boxes[0]["label"] if boxes else None, boxes=boxes)
            row.update({f"{prefix}_{k}": v for k, v in record.items()})
        rows.append(row)
    return rows


def evaluate(textures: Mapping[str, Texture], scenes: Sequence[Path], victims: Sequence[str], sim: str = "mitsuba",
             spp: int = 32, holdout: Any = "auto", label: str | None = None, seed: int = 0,
             local: LocalSettings = LocalSettings(), per_frame: list[dict[str, Any]] | None = None,
             capture: Any = None, defence: Any = None) -> list[dict[str, Any]]:
    """One row per (scene, victim, texture, split ``all``/``attacked``/``held_out``, and ``condition NAME``
    for each condition of a multi-condition scene directory): frames, metric,
    the scene's own texture's value (``benign``) and the texture's (``adversarial``), fractions in
    [0, 1]. ``textures``: name → (texture, the scene directory it was optimised on or None), whose
    object's UV layout every scene's must share (:func:`check_uv_layout`). ``per_frame``: a list that
    receives one row per (scene, victim, texture, frame) as well (:func:`frame_rows`). ``capture``: a
    :class:`undream.spec.physical.PrintEotConfig`: every texture, the scene's own too, is judged printed
    and captured, one draw per frame that no attack drew (:func:`undream.engine.algorithm.captured_frames`).
    ``defence``: a :class:`undream.spec.defence.DefenceConfig`: each victim judges behind it (a row's
    ``victim`` then reads ``NAME + jpeg 75``)."""
    from undream.engine.algorithm import start_texture
    from undream.engine.context import build_context
    from undream.engine.patch import judge_splits, texture_predictions
    from undream.victims import load_victim

    # an unknown victim fails before any render
    loaded = {name: load_victim(name, cache_home=local.cache_home) for name in victims}
    rows = []
    with tempfile.TemporaryDirectory(prefix="undream-evaluate-") as tmp:
        dirs = [_scene_dir(Path(scene), Path(tmp), local) for scene in scenes]
        references = {reference for _, reference in textures.values() if reference is not None}  # a sweep's: one
        for scene, scene_dir in zip(scenes, dirs):
            for reference in references:
                check_uv_layout(reference, scene_dir, Path(scene))
        contexts = []
        try:
            for scene, scene_dir in zip(scenes, dirs):  # every scene checked before anything renders
                for name, victim in loaded.items():
                    # the loss names the victim's task, and a detector is judged against the object's
                    # box in each frame (without it, AP had no ground truth and every cell was n/a)
                    config = RunConfig.from_json({"scene": str(scene_dir), "name": "evaluate", "victim": name,
                                                  "label": label, "eval_spp": spp, "holdout": holdout,
                                                  "sim": sim, "seed": seed, "loss": TASK_LOSSES[victim.task][0],
                                                  "defence": None if defence is None else defence.to_json()})
                    shown = name if defence is None else f"{name} + {defence.label}"
                    contexts.append((scene, shown, build_context(config, scene_dir, victim=victim, local=local)))
                    wanted = contexts[-1][2].sequence.texture.shape
                    for texture_name, (texture, _) in textures.items():
                        if wanted != texture.shape:
                            raise SpecError(f"TEXTURE {texture_name}: {texture.shape[1]}×{texture.shape[0]} texels, "
                                            f"but scene {scene}'s texture is {wanted[1]}×{wanted[0]}: a texture "
                                            "made for another object or UV layout")
            for scene, name, ctx in contexts:
                parts = split_conditions(holdout, ctx.sequence.condition_ranges())
                splits = {"all": sorted(parts.attacked + parts.held), "attacked": parts.attacked, "held_out": parts.held}
                if ctx.sequence.conditions:  # a multi-condition scene: a row per condition too
                    splits.update({f"condition {part.name}": list(span) for part, span in ctx.sequence.condition_ranges()})
                benign_preds = texture_predictions(ctx, start_texture(ctx), capture)
                benign = judge_splits(ctx, benign_preds, splits)
                for texture_name, (texture, _) in textures.items():
                    preds = texture_predictions(ctx, texture, capture)
                    for split, judged in judge_splits(ctx, preds, splits).items():
                        rows.append({"scene": str(scene), "victim": name, "sim": sim, "texture": texture_name,
                                     "split": split, "frames": len(judged["frames"]), "metric": judged["metric"],
                                     "benign": benign[split]["value"], "adversarial": judged["value"]})
                    if per_frame is not None:
                        head = {"scene": str(scene), "victim": name, "sim": sim, "texture": texture_name}
                        per_frame.extend({**head, **r} for r in frame_rows(ctx, parts, benign_preds, preds))
        finally:
            for _, _, ctx in contexts:
                ctx.scenes.close()
    return rows
