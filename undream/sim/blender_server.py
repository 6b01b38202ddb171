"""The Cycles render server: ``python -m undream.sim.blender_server SCENE_DIR [--threads N]``.

Runs in Blender's own environment (``.venv-blender``: Python 3.11, ``bpy``
5.0.1, numpy < 2), never in undream's: it imports bpy, numpy and the light
parts of undream (spec, PLY reader, the Mitsuba scene *dictionaries*), no
Mitsuba, torch or celery. It loads the scene directory once, answers with a
``ready`` message (versions; ``threads``: the CPU threads Cycles renders
with: ``--threads`` N > 0 fixed, 0 Blender's count of all cores), then serves
requests on stdin/stdout in the format of :mod:`undream.sim.blender_protocol`:

- ``{"cmd": "render", "index", "spp", "seed"}`` + H×W×3 float32 texture
  (LINEAR reflectance) → ``{"ok": true, "seconds"}`` + H×W×3 float32 frame
  (linear radiance);
- ``{"cmd": "coverage", "index", "spp"}`` → H×W float32: the object's
  visible coverage in [0, 1] (its mask is coverage > 0.5);
- ``{"cmd": "quit"}`` → exits.

A failed request answers ``{"error": "one line"}`` and the server goes on.
Blender writes its own log lines to file descriptor 1: the protocol keeps a
private duplicate of stdout and points fd 1 at stderr before bpy loads.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import BinaryIO

from undream.sim.blender_protocol import ProtocolError, read_message, write_message


def _protocol_stdout() -> BinaryIO:
    """A private binary stream on the real stdout; fd 1 then goes to stderr (Blender's chatter)."""
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    sys.stdout.flush()
    os.dup2(2, 1)
    return out


def serve(scene_dir: str, threads: int, inp: BinaryIO, out: BinaryIO) -> None:
    """Load ``scene_dir`` and answer requests until ``quit`` or the end of ``inp``."""
    try:
        from undream.sim.blender_scene import CyclesScene

        scene = CyclesScene(scene_dir, threads)
    except Exception as err:  # reported to the client as one line, then the server exits
        write_message(out, {"error": f"loading {scene_dir}: {type(err).__name__}: {err}"})
        return
    write_message(out, {"ready": True, "versions": scene.versions(), "threads": scene.threads()})
    while True:
        try:
            header, array = read_message(inp)
        except ProtocolError:
            return  # the client went away
        cmd = header.get("cmd")
        if cmd == "quit":
            return
        if not (cmd == "render" and array is not None or cmd == "coverage"):
            write_message(out, {"error": f"unknown request {cmd!r} (render with a texture, coverage, or quit)"})
            continue
        try:
            t0 = time.perf_counter()
            if cmd == "coverage":
                img = scene.coverage(int(header["index"]), int(header["spp"]))
            else:
                img = scene.render(int(header["index"]), array, int(header["spp"]), int(header["seed"]))
            write_message(out, {"ok": True, "seconds": time.perf_counter() - t0}, img)
        except Exception as err:  # one line back; the scene stays loaded for the next request
            write_message(out, {"error": f"{type(err).__name__}: {err}"})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene_dir")
    parser.add_argument("--threads", type=int, default=0, help="Cycles CPU threads (0: all cores)")
    args = parser.parse_args(argv)
    out = _protocol_stdout()
    serve(args.scene_dir, args.threads, sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
