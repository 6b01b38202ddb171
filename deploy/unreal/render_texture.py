"""Render undream textures in Unreal Engine (editor Python): one texture version, or serve ``sim: unreal``.

Targets the Unreal Editor's Python plugin of Unreal Engine 5.1 to 5.5 with
the Movie Render Queue plugin enabled. The adversarial object's material is
a Material Instance Constant whose base colour samples a texture parameter
(sampler type *Color*: the PNG is sRGB). Two modes, in the editor's Output
Log (Python) or with ``UnrealEditor Project.uproject -ExecutePythonScript="..."``:

Render one texture version (a PNG that undream wrote, e.g. ``texture_final.png``)
over the Level Sequence, one image per frame::

    py "<undream>/deploy/unreal/render_texture.py" --texture D:/runs/bin/texture_final.png
        --material /Game/Undream/MI_AdvBin --parameter AdvTexture --sequence /Game/Seq/DriveBy
        --out D:/renders/drive_by [--start 0 --end 8] [--format png|exr] [--spp 8] [--resolution 1920 1080]

Serve the frame jobs of undream runs with ``sim: unreal`` (the worker beside
the editor; undream's side is ``undream/sim/unreal.py``, the protocol is in
``docs/unreal.md``)::

    py "<undream>/deploy/unreal/render_texture.py" --spool S:/undream-spool
        --material /Game/Undream/MI_AdvBin --parameter AdvTexture --sequence /Game/Seq/DriveBy [--format exr]

The worker claims one request at a time (``requests/ID.json`` → ``ID.json.taken``),
imports the request's texture (``unreal.AssetImportTask``, uncompressed, into
``--texture-folder``), sets it on the material instance
(``MaterialEditingLibrary.set_material_instance_texture_parameter_value``),
renders the requested frame with Movie Render Queue
(``MoviePipelineQueueSubsystem``, ``MoviePipelinePIEExecutor``: the frame
range ``[frame, frame + 1)`` at the request's resolution, ``spp`` spatial
samples, no temporal samples) and writes ``responses/ID.exr`` (linear) or
``.png`` (sRGB), then ``responses/ID.json``. It runs on Slate's tick, so the
editor stays responsive; ``py render_texture.py --stop`` ends it.

Everything but :class:`UnrealRenderer` is plain Python (standard library),
tested without Unreal (``tests/test_sim_unreal.py``) against a stand-in
renderer that answers from recorded frames.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Protocol, Sequence

REQUEST_FORMAT = "undream-unreal-request"
RESPONSE_FORMAT = "undream-unreal-response"
WORKER_FORMAT = "undream-unreal-worker"
VERSION = 1
FORMATS = {"exr": ("MoviePipelineImageSequenceOutput_EXR", "exr", "linear"),
           "png": ("MoviePipelineImageSequenceOutput_PNG", "png", "srgb")}
_ID = re.compile(r"[A-Za-z0-9_.-]{1,200}")

Done = Callable[[Optional[Path], Optional[str]], None]  # (frame file, None) or (None, one-line error)


class RequestError(ValueError):
    """A request this worker cannot serve (one line; it becomes the response's ``error``)."""


@dataclass(frozen=True)
class Job:
    """One frame to render: what a request asks for."""

    id: str
    sequence: str  # undream's sequence name (informative: the worker renders its --sequence)
    frame: int  # the Level Sequence's display-rate frame number
    resolution: tuple[int, int]  # output (width, height) in pixels
    spp: int  # Movie Render Queue spatial samples
    seed: int
    texture: Path  # the texture PNG (sRGB, 8 bits per channel)


def parse_request(data: Any, folder: Path) -> Job:
    """The :class:`Job` of a request's JSON (read from ``folder``); :class:`RequestError` names what is wrong."""
    if not isinstance(data, dict):
        raise RequestError("the request must be a JSON object")
    if data.get("format") != REQUEST_FORMAT or data.get("version") != VERSION:
        raise RequestError(f"unsupported request: format {data.get('format')!r} version {data.get('version')!r} "
                           f"(this worker serves {REQUEST_FORMAT!r} version {VERSION})")
    for key in ("id", "sequence", "frame", "resolution", "spp", "seed", "texture"):
        if key not in data:
            raise RequestError(f"the request has no {key!r}")
    rid, texture = data["id"], data["texture"]
    if not isinstance(rid, str) or not _ID.fullmatch(rid):
        raise RequestError(f"id: must be letters, digits, '_', '-' or '.', got {rid!r}")
    res = data["resolution"]
    if not (isinstance(res, list) and len(res) == 2 and all(isinstance(v, int) and 1 <= v <= 16384 for v in res)):
        raise RequestError(f"resolution: must be [width, height] in pixels, got {res!r}")
    for key in ("frame", "spp", "seed"):
        if isinstance(data[key], bool) or not isinstance(data[key], int) or data[key] < (1 if key == "spp" else 0):
            raise RequestError(f"{key}: must be an integer >= {1 if key == 'spp' else 0}, got {data[key]!r}")
    if not isinstance(texture, str) or Path(texture).name != texture or not texture.lower().endswith(".png"):
        raise RequestError(f"texture: must name a .png file beside the request, got {texture!r}")
    if not (folder / texture).is_file():
        raise RequestError(f"texture: {folder / texture} not found")
    return Job(rid, str(data["sequence"]), data["frame"], (res[0], res[1]), data["spp"], data["seed"],
               folder / texture)


def _write_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


class Spool:
    """The shared folder: ``requests/`` (undream writes), ``responses/`` (this worker writes), ``worker.json``."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.requests, self.responses = self.root / "requests", self.root / "responses"
        for folder in (self.requests, self.responses):
            folder.mkdir(parents=True, exist_ok=True)

    def announce(self, info: dict[str, Any]) -> None:
        """Write ``worker.json`` (engine version, project, sequence): undream records it in metadata.json."""
        _write_atomically(self.root / "worker.json",
                          json.dumps({"format": WORKER_FORMAT, "version": VERSION, **info}))

    def claim(self) -> Optional[Job]:
        """The oldest unclaimed request, claimed (renamed ``ID.json.taken``); None when there is none.

        A request that cannot be served is answered with an error at once and
        None is returned for it (the next call looks again).
        """
        waiting = []
        for path in self.requests.glob("*.json"):
            try:
                waiting.append((path.stat().st_mtime, path.name, path))
            except FileNotFoundError:  # claimed by another worker meanwhile
                continue
        for _, _, path in sorted(waiting):
            taken = path.with_name(path.name + ".taken")
            try:
                os.replace(path, taken)  # atomic: of two workers on one spool, one wins
            except FileNotFoundError:
                continue
            try:
                return parse_request(json.loads(taken.read_text(encoding="utf-8")), self.requests)
            except (RequestError, ValueError, OSError) as err:
                self.fail(path.stem, " ".join(str(err).split()))
                return None
        return None

    def respond(self, job: Job, frame: Path, space: str, seconds: float, engine: str) -> None:
        """Move the rendered ``frame`` into ``responses/ID.<ext>``, then write ``responses/ID.json``."""
        image = f"{job.id}{frame.suffix.lower()}"
        shutil.move(str(frame), str(self.responses / image))
        _write_atomically(self.responses / f"{job.id}.json", json.dumps({
            "format": RESPONSE_FORMAT, "version": VERSION, "id": job.id, "image": image, "space": space,
            "seconds": round(seconds, 3), "engine": engine}))

    def fail(self, rid: str, message: str) -> None:
        """Answer request ``rid`` with a one-line error."""
        _write_atomically(self.responses / f"{rid}.json", json.dumps({
            "format": RESPONSE_FORMAT, "version": VERSION, "id": rid, "error": " ".join(message.split())}))


class Renderer(Protocol):
    """What :class:`Worker` needs from Unreal (see :class:`UnrealRenderer`)."""

    space: str  # "linear" (EXR frames) or "srgb" (PNG frames)

    def engine(self) -> str:
        """The engine version, for the responses."""
        ...

    def render(self, job: Job, done: Done) -> None:
        """Render ``job`` with its texture; call ``done(frame_file, None)`` or ``done(None, error)``, now or later."""
        ...


class Worker:
    """Serves a :class:`Spool` with a :class:`Renderer`, one job at a time; call :meth:`tick` often."""

    def __init__(self, spool: Spool, renderer: Renderer) -> None:
        self.spool, self.renderer = spool, renderer
        self.busy: Optional[Job] = None
        self.started = 0.0
        self.served = 0

    def tick(self) -> None:
        """Start the next job if idle (Slate's post-tick callback in the editor; a loop in tests)."""
        if self.busy is not None:
            return
        job = self.spool.claim()
        if job is None:
            return
        self.busy, self.started = job, time.monotonic()
        try:
            self.renderer.render(job, lambda frame, error: self._done(job, frame, error))
        except Exception as err:  # reported to undream as one line; the worker goes on
            self._done(job, None, f"{type(err).__name__}: {err}")

    def _done(self, job: Job, frame: Optional[Path], error: Optional[str]) -> None:
        if self.busy is not job:
            return  # a late second callback
        try:
            if error is not None or frame is None or not frame.is_file():
                self.spool.fail(job.id, error or f"the render wrote no frame for {job.id}")
            else:
                self.spool.respond(job, frame, self.renderer.space, time.monotonic() - self.started,
                                   self.renderer.engine())
                self.served += 1
        finally:
            self.busy = None


# --- Unreal ------------------------------------------------------------------------------------

class UnrealRenderer:
    """Imports textures, sets them on the material instance and renders frames with Movie Render Queue.

    The only code that calls ``unreal``.
    """

    def __init__(self, sequence: str, material: str, parameter: str, texture_folder: str,
                 fmt: str = "exr", level: Optional[str] = None) -> None:
        import unreal  # Unreal API (editor only)

        self.u = unreal
        self.sequence = _object_path(sequence)
        if unreal.load_asset(self.sequence) is None:
            raise ValueError(f"--sequence: no Level Sequence at {sequence!r}")
        self.material = unreal.load_asset(material)
        if not isinstance(self.material, unreal.MaterialInstanceConstant):
            raise ValueError(f"--material: {material!r} is not a Material Instance Constant")
        self.parameter, self.folder = parameter, texture_folder.rstrip("/")
        self.fmt = fmt
        self.space = FORMATS[fmt][2]
        self.level = level or _editor_level(unreal)
        self.subsystem = unreal.get_editor_subsystem(unreal.MoviePipelineQueueSubsystem)
        self._active: dict[str, Any] = {}  # keeps executor, queue and callbacks alive while rendering

    def engine(self) -> str:
        return str(self.u.SystemLibrary.get_engine_version())

    def set_texture(self, png: Path, name: str) -> None:
        """Import ``png`` as ``<texture folder>/<name>`` (uncompressed sRGB) and set it on the material."""
        u = self.u
        task = u.AssetImportTask()
        task.set_editor_property("filename", str(png))
        task.set_editor_property("destination_path", self.folder)
        task.set_editor_property("destination_name", name)
        task.set_editor_property("replace_existing", True)
        task.set_editor_property("automated", True)
        task.set_editor_property("save", False)
        u.AssetToolsHelpers.get_asset_tools().import_asset_tasks([task])
        paths = list(task.get_editor_property("imported_object_paths") or [])
        texture = u.load_asset(paths[0]) if paths else None
        if not isinstance(texture, u.Texture2D):
            raise RuntimeError(f"importing {png} as a texture failed (see the Output Log)")
        texture.set_editor_property("srgb", True)
        texture.set_editor_property("compression_settings", u.TextureCompressionSettings.TC_EDITOR_ICON)
        lib = u.MaterialEditingLibrary
        if not lib.set_material_instance_texture_parameter_value(self.material, self.parameter, texture):
            raise RuntimeError(f"the material instance has no texture parameter {self.parameter!r}")
        lib.update_material_instance(self.material)

    def render_range(self, start: int, end: int, resolution: tuple[int, int], spp: int, out_dir: Path,
                     done: Callable[[bool, str], None]) -> None:
        """Render display-rate frames ``[start, end)`` as ``out_dir/NNNN.<ext>``; ``done(success, error)`` later."""
        u = self.u
        if self._active or self.subsystem.is_rendering():
            raise RuntimeError("Movie Render Queue is already rendering")
        out_dir.mkdir(parents=True, exist_ok=True)
        queue = u.MoviePipelineQueue()
        job = queue.allocate_new_job(u.MoviePipelineExecutorJob)
        job.set_editor_property("job_name", "undream")
        job.set_editor_property("sequence", u.SoftObjectPath(self.sequence))
        job.set_editor_property("map", u.SoftObjectPath(self.level))
        config = job.get_configuration()
        out = config.find_or_add_setting_by_class(u.MoviePipelineOutputSetting)
        directory = u.DirectoryPath()
        directory.set_editor_property("path", str(out_dir).replace("\\", "/"))
        out.set_editor_property("output_directory", directory)
        out.set_editor_property("file_name_format", "{frame_number}")
        out.set_editor_property("zero_pad_frame_numbers", 4)
        out.set_editor_property("output_resolution", u.IntPoint(*resolution))
        out.set_editor_property("use_custom_playback_range", True)
        out.set_editor_property("custom_start_frame", start)
        out.set_editor_property("custom_end_frame", end)  # exclusive
        out.set_editor_property("override_existing_output", True)
        aa = config.find_or_add_setting_by_class(u.MoviePipelineAntiAliasingSetting)
        aa.set_editor_property("spatial_sample_count", spp)
        aa.set_editor_property("temporal_sample_count", 1)
        aa.set_editor_property("override_anti_aliasing", True)
        aa.set_editor_property("anti_aliasing_method", u.AntiAliasingMethod.AAM_NONE)
        config.find_or_add_setting_by_class(u.MoviePipelineDeferredPassBase)
        config.find_or_add_setting_by_class(getattr(u, FORMATS[self.fmt][0]))
        executor = u.MoviePipelinePIEExecutor(self.subsystem)
        errors: list[str] = []

        def errored(_executor: Any, _pipeline: Any, fatal: bool, text: Any) -> None:
            if fatal:
                errors.append(str(text))

        def finished(_executor: Any, success: bool) -> None:
            self._active.clear()
            done(bool(success) and not errors, "; ".join(errors) or ("" if success else "the render failed"))

        executor.on_executor_errored_delegate.add_callable_unique(errored)
        executor.on_executor_finished_delegate.add_callable_unique(finished)
        self._active.update(executor=executor, queue=queue, errored=errored, finished=finished)
        render = getattr(self.subsystem, "render_queue_instance_with_executor_instance", None)
        if render is not None:
            render(queue, executor)
        else:
            executor.execute(queue)

    def render(self, job: Job, done: Done) -> None:
        """One request: its texture on the material, frame ``job.frame`` rendered into a temporary folder."""
        self.set_texture(job.texture, f"T_undream_{re.sub(r'[^A-Za-z0-9_]', '_', job.id)}")
        out_dir = Path(tempfile.mkdtemp(prefix="undream-mrq-"))
        frame = out_dir / f"{job.frame:04d}.{FORMATS[self.fmt][1]}"

        def finished(success: bool, error: str) -> None:
            done(frame if success and frame.is_file() else None, None if success else error)

        self.render_range(job.frame, job.frame + 1, job.resolution, job.spp, out_dir, finished)


def _object_path(path: str) -> str:
    """``/Game/Seq/DriveBy.DriveBy`` for ``/Game/Seq/DriveBy`` (MRQ needs the object, not the package)."""
    name = path.rstrip("/").rsplit("/", 1)[-1]
    return path if "." in name else f"{path}.{name}"


def _editor_level(u: Any) -> str:
    world = u.get_editor_subsystem(u.UnrealEditorSubsystem).get_editor_world()
    path = str(world.get_path_name()) if world is not None else ""
    if not path or path.startswith("/Temp/"):
        raise ValueError("the open level has never been saved (Movie Render Queue renders a saved level); "
                         "save it or pass --level")
    return path


# --- entry point -------------------------------------------------------------------------------

def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="render_texture.py", description="Render undream textures in Unreal.")
    p.add_argument("--stop", action="store_true", help="stop a running --spool worker")
    p.add_argument("--spool", help="serve sim: unreal requests from this shared folder")
    p.add_argument("--texture", help="render this texture version (PNG) once")
    p.add_argument("--out", help="with --texture: the folder for the frames (NNNN.png or .exr)")
    p.add_argument("--sequence", help="the Level Sequence, e.g. /Game/Seq/DriveBy")
    p.add_argument("--material", help="the object's Material Instance Constant")
    p.add_argument("--parameter", default="AdvTexture", help="its texture parameter (default AdvTexture)")
    p.add_argument("--texture-folder", default="/Game/Undream/Textures", help="where textures are imported")
    p.add_argument("--level", help="the level to render (default: the one open in the editor)")
    p.add_argument("--format", choices=sorted(FORMATS), default="exr")
    p.add_argument("--spp", type=int, default=8, help="spatial samples per pixel (--texture mode)")
    p.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=(1920, 1080))
    p.add_argument("--start", type=int, help="--texture mode: first frame (default: the playback start)")
    p.add_argument("--end", type=int, help="--texture mode: end frame, exclusive (default: the playback end)")
    args = p.parse_args(list(argv))
    if args.stop:
        return args
    if bool(args.spool) == bool(args.texture):
        p.error("give either --spool DIR (serve undream) or --texture PNG --out DIR (render once)")
    if args.texture and not args.out:
        p.error("--texture needs --out DIR")
    for name in ("sequence", "material"):
        if not getattr(args, name):
            p.error(f"--{name} is required")
    if args.spp < 1:
        p.error("--spp must be >= 1")
    return args


_SERVING: dict[str, Any] = {}  # the running worker and its tick handle (module state survives between `py` calls)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point in the editor (see the module docstring)."""
    import sys

    import unreal

    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.stop or args.spool:
        if "handle" in _SERVING:
            unreal.unregister_slate_post_tick_callback(_SERVING.pop("handle"))
            unreal.log("undream: the spool worker stopped")
        if args.stop:
            return
    renderer = UnrealRenderer(args.sequence, args.material, args.parameter, args.texture_folder, args.format,
                              args.level)
    if args.spool:
        spool = Spool(args.spool)
        spool.announce({"engine": renderer.engine(), "project": str(unreal.Paths.get_project_file_path()),
                        "sequence": args.sequence, "material": args.material, "format": args.format})
        worker = Worker(spool, renderer)
        _SERVING.update(worker=worker, handle=unreal.register_slate_post_tick_callback(lambda _dt: worker.tick()))
        unreal.log(f"undream: serving {spool.root} with {args.sequence}")
        return
    sequence = unreal.load_asset(renderer.sequence)
    start = sequence.get_playback_start() if args.start is None else args.start
    end = sequence.get_playback_end() if args.end is None else args.end
    renderer.set_texture(Path(args.texture), "T_undream_" + re.sub(r"[^A-Za-z0-9_]", "_", Path(args.texture).stem))
    renderer.render_range(start, end, tuple(args.resolution), args.spp, Path(args.out),
                          lambda ok, error: unreal.log(f"undream: frames {start}..{end - 1} in {args.out}") if ok
                          else unreal.log_error(f"undream: the render failed: {error}"))


if __name__ == "__main__":
    main()
