"""Export a Level Sequence as an ``undream-unreal-export`` JSON file (Unreal editor Python).

Targets the Unreal Editor's Python plugin of Unreal Engine 5.1 to 5.5
(``set_global_position`` from 5.4, ``set_current_time`` before it). Run it in
the editor (the Sequencer editor must exist, so not as a commandlet)::

    py "<undream>/deploy/unreal/export_sequence.py" --sequence /Game/Seq/DriveBy
        --config D:/undream/drive_by_config.json --resolution 1920 1080
        --out D:/undream/drive_by.json

or ``UnrealEditor.exe Project.uproject -ExecutePythonScript="<same command line>"``.
``--mrq-config /Game/Cinematics/MRQ_Preset`` reads the output resolution from a
Movie Render Queue preset instead of ``--resolution``. The config names the
actors (by their labels in the Outliner) and their undream assets::

    {"camera": "CineCam",
     "object": {"actor": "AdvBin", "asset": {"name": "bin", "mesh": "builtin:trash_bin",
                                              "texture": {"resolution": [256, 256]}}},
     "actors": [{"actor": "Car1", "asset": {"name": "car1", "mesh": "builtin:car"}}],
     "environment": {"weather": "clear", "time_of_day": 15.5}}

For every display-rate frame of the playback range the script moves
Sequencer's playhead there, which evaluates every track as Unreal renders it
(cubic and intermediate keys, attachments, constraints, rigs), and only then
reads each actor's world transform (cm, FRotator degrees, scale) and the cine
camera component's world pose, horizontal field of view (degrees, over the
filmback width) and filmback (mm). Nothing is interpolated here.

The module imports ``unreal`` only inside :class:`UnrealScene`, the one class
that calls Unreal's API; everything else is plain Python, unit-tested without
Unreal (``tests/test_unreal_import.py``). The format is documented in
``undream/bridge/unreal_import.py`` and ``docs/unreal.md``.
"""
from __future__ import annotations

import argparse
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

FORMAT = "undream-unreal-export"
VERSION = 1

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class CameraSample:
    """The camera at one frame: Unreal world pose (cm, degrees) and optics."""

    location_cm: Vec3
    rotation_rpy_deg: Vec3  # (roll, pitch, yaw)
    fov_deg: float  # horizontal, over the filmback width
    filmback_mm: tuple[float, float]  # sensor (width, height)


@dataclass(frozen=True)
class TransformSample:
    """An actor's Unreal world transform: location cm, rotation degrees, scale."""

    location_cm: Vec3
    rotation_rpy_deg: Vec3  # (roll, pitch, yaw)
    scale: Vec3 = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class FrameSample:
    """Everything read at one display-rate frame."""

    frame: int
    time: float  # seconds since the playback start
    camera: CameraSample
    transforms: Mapping[str, TransformSample]  # actor label -> transform


class Scene(Protocol):
    """What :func:`sample_frames` needs from Unreal (see :class:`UnrealScene`)."""

    def go_to(self, frame: int) -> None: ...
    def camera(self, label: str) -> CameraSample: ...
    def transform(self, label: str) -> TransformSample: ...


# --- pure part: config, sampling loop, JSON ------------------------------------------

def check_config(config: Any) -> dict[str, Any]:
    """Validate the exporter config (see the module docstring); ValueError names the field."""
    if not isinstance(config, Mapping):
        raise ValueError(f"config: must be a JSON object, got {config!r}")
    extra = sorted(set(config) - {"camera", "object", "actors", "environment"})
    if extra:
        raise ValueError(f"config.{extra[0]}: unknown field (valid: actors, camera, environment, object)")
    if not isinstance(config.get("camera"), str) or not config["camera"]:
        raise ValueError(f"config.camera: must be the cine camera actor's label, got {config.get('camera')!r}")
    if not isinstance(config.get("actors", []), list):
        raise ValueError(f"config.actors: must be a list, got {config['actors']!r}")
    entries = [("object", config.get("object"))]
    entries += [(f"actors[{i}]", a) for i, a in enumerate(config.get("actors", []))]
    for where, entry in entries:
        if (not isinstance(entry, Mapping) or not isinstance(entry.get("actor"), str)
                or not isinstance(entry.get("asset"), Mapping)):
            raise ValueError(f"config.{where}: must be {{\"actor\": LABEL, \"asset\": {{...}}}}, got {entry!r}")
    return dict(config)


def actor_labels(config: Mapping[str, Any]) -> list[str]:
    """Labels of the object and the extra actors, object first."""
    return [config["object"]["actor"], *(a["actor"] for a in config.get("actors", []))]


def frame_numbers(start: int, end_exclusive: int, every: int = 1) -> list[int]:
    """Display-rate frames of a playback range ``[start, end_exclusive)``, every ``every``-th."""
    if every < 1:
        raise ValueError(f"every: must be >= 1, got {every}")
    if end_exclusive <= start:
        raise ValueError(f"playback range [{start}, {end_exclusive}) is empty")
    return list(range(start, end_exclusive, every))


def sample_frames(scene: Scene, frames: Sequence[int], start: int, fps: float,
                  camera: str, actors: Sequence[str]) -> list[FrameSample]:
    """Move the playhead to each frame, then read the camera and the actors there."""
    samples = []
    for f in frames:
        scene.go_to(f)
        transforms = {label: scene.transform(label) for label in actors}
        samples.append(FrameSample(f, (f - start) / fps, scene.camera(camera), transforms))
    return samples


def _vec(v: Sequence[float]) -> list[float]:
    return [float(x) for x in v]


def transform_json(t: TransformSample) -> dict[str, list[float]]:
    return {"location": _vec(t.location_cm), "rotation": _vec(t.rotation_rpy_deg), "scale": _vec(t.scale)}


def camera_json(c: CameraSample, resolution: tuple[int, int]) -> dict[str, Any]:
    return {"location": _vec(c.location_cm), "rotation": _vec(c.rotation_rpy_deg),
            "fov": float(c.fov_deg), "filmback": _vec(c.filmback_mm),
            "resolution": [int(resolution[0]), int(resolution[1])]}


def build_export(config: Mapping[str, Any], sequence_path: str, fps: float,
                 resolution: tuple[int, int], samples: Sequence[FrameSample]) -> dict[str, Any]:
    """The export JSON (a dict) from the config and the per-frame samples."""
    data: dict[str, Any] = {"format": FORMAT, "version": VERSION, "sequence": sequence_path,
                            "fps": float(fps), "camera": {"name": config["camera"]},
                            "object": config["object"], "actors": list(config.get("actors", []))}
    if config.get("environment"):
        data["environment"] = config["environment"]
    data["frames"] = [{"frame": s.frame, "time": s.time,
                       "camera": camera_json(s.camera, resolution),
                       "transforms": {k: transform_json(t) for k, t in s.transforms.items()}}
                      for s in samples]
    return data


_NUMBER_LIST = re.compile(r"\[\s*((?:-?[\w.+-]+,\s*)*-?[\w.+-]+)\s*\]")


def write_export(data: Mapping[str, Any], path: str | Path) -> None:
    """Write the export, one vector per line; NaN stays NaN so that the importer names the field."""
    text = json.dumps(data, indent=1)
    text = _NUMBER_LIST.sub(lambda m: "[" + re.sub(r",\s*", ", ", m.group(1)) + "]", text)
    Path(path).write_text(text + "\n", encoding="utf-8")


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="export_sequence.py", description="Export a Level Sequence for undream.")
    p.add_argument("--sequence", required=True, help="Level Sequence asset path, e.g. /Game/Seq/DriveBy")
    p.add_argument("--config", required=True, help="JSON naming the camera, object and actors")
    p.add_argument("--out", required=True, help="output .json file")
    res = p.add_mutually_exclusive_group(required=True)
    res.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), help="output pixels")
    res.add_argument("--mrq-config", help="Movie Render Queue preset to read the resolution from")
    p.add_argument("--start", type=int, help="first frame (default: playback start)")
    p.add_argument("--end", type=int, help="end frame, exclusive (default: playback end)")
    p.add_argument("--every", type=int, default=1, help="export every N-th frame")
    return p.parse_args(list(argv))


# --- Unreal API: everything below runs only inside the editor ----------------------

class UnrealScene:
    """The Level Sequence opened in Sequencer; the only code that calls ``unreal``."""

    def __init__(self, sequence_path: str) -> None:
        import unreal  # Unreal API (editor only)

        self.u = unreal
        self.lib = unreal.LevelSequenceEditorBlueprintLibrary
        self.sequence = unreal.load_asset(sequence_path)
        if not isinstance(self.sequence, unreal.LevelSequence):
            raise ValueError(f"--sequence: no Level Sequence at {sequence_path!r}")
        self.lib.open_level_sequence(self.sequence)  # evaluates into the editor world
        self._level_actors: dict[str, Any] | None = None

    def playback(self) -> tuple[int, int, float]:
        """(start, end exclusive) display-rate frames and the display rate in frames/s."""
        rate = self.sequence.get_display_rate()
        fps = rate.numerator / rate.denominator
        return self.sequence.get_playback_start(), self.sequence.get_playback_end(), fps

    def go_to(self, frame: int) -> None:
        """Move the playhead to ``frame`` (display rate) and evaluate the sequence there."""
        u, lib = self.u, self.lib
        if hasattr(lib, "set_global_position"):  # UE 5.4+
            params = u.MovieSceneSequencePlaybackParams(
                frame=u.FrameTime(u.FrameNumber(frame)), position_type=u.MovieScenePositionType.FRAME,
                update_method=u.UpdatePositionMethod.JUMP)
            lib.set_global_position(params, u.MovieSceneTimeUnit.DISPLAY_RATE)
        else:  # UE 5.1-5.3
            lib.set_current_time(frame)
        if hasattr(lib, "force_update"):
            lib.force_update()

    def _actor(self, label: str) -> Any:
        for binding in self.sequence.get_bindings():  # possessables and spawnables
            for obj in self.lib.get_bound_objects(self.sequence.get_binding_id(binding)):
                if isinstance(obj, self.u.Actor) and obj.get_actor_label() == label:
                    return obj
        if self._level_actors is None:  # actors the sequence does not animate
            sub = self.u.get_editor_subsystem(self.u.EditorActorSubsystem)
            self._level_actors = {a.get_actor_label(): a for a in sub.get_all_level_actors()}
        if label not in self._level_actors:
            raise ValueError(f"no actor labelled {label!r} in the sequence or the level")
        return self._level_actors[label]

    def transform(self, label: str) -> TransformSample:
        actor = self._actor(label)
        loc, rot, scale = actor.get_actor_location(), actor.get_actor_rotation(), actor.get_actor_scale3d()
        return TransformSample((loc.x, loc.y, loc.z), (rot.roll, rot.pitch, rot.yaw),
                               (scale.x, scale.y, scale.z))

    def camera(self, label: str) -> CameraSample:
        comp = self._actor(label).get_component_by_class(self.u.CineCameraComponent)
        if comp is None:
            raise ValueError(f"actor {label!r} has no CineCameraComponent")
        loc, rot = comp.get_world_location(), comp.get_world_rotation()
        filmback = comp.get_editor_property("filmback")
        size = (filmback.sensor_width, filmback.sensor_height)
        fov = comp.get_horizontal_field_of_view()
        if comp.get_editor_property("constrain_aspect_ratio"):
            self.u.log_warning(f"{label}: 'Constrain Aspect Ratio' letterboxes Unreal's frames when "
                               "the output aspect differs from the filmback; undream crops instead")
        return CameraSample((loc.x, loc.y, loc.z), (rot.roll, rot.pitch, rot.yaw), fov, size)

    def resolution_from_mrq(self, preset_path: str) -> tuple[int, int]:
        preset = self.u.load_asset(preset_path)
        setting = preset.find_setting_by_class(self.u.MoviePipelineOutputSetting) if preset else None
        if setting is None:
            raise ValueError(f"--mrq-config: no Movie Render Queue output setting in {preset_path!r}")
        return setting.output_resolution.x, setting.output_resolution.y

    def close(self) -> None:
        self.lib.close_level_sequence()


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point in the editor: ``py export_sequence.py --sequence ... --out ...``."""
    import sys

    args = parse_args(sys.argv[1:] if argv is None else argv)
    config = check_config(json.loads(Path(args.config).read_text(encoding="utf-8")))
    scene = UnrealScene(args.sequence)
    try:
        start, end, fps = scene.playback()
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"display rate: must be > 0 frames/s, got {fps}")
        resolution = ((args.resolution[0], args.resolution[1]) if args.resolution
                      else scene.resolution_from_mrq(args.mrq_config))
        frames = frame_numbers(start if args.start is None else args.start,
                               end if args.end is None else args.end, args.every)
        samples = sample_frames(scene, frames, start, fps, config["camera"], actor_labels(config))
    finally:
        scene.close()
    write_export(build_export(config, args.sequence, fps, resolution, samples), args.out)


if __name__ == "__main__":
    main()
