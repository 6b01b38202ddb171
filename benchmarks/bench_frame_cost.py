#!/usr/bin/env python
"""What one whole frame costs the simulator, by weather and samples per pixel.

    .venv/bin/python benchmarks/bench_frame_cost.py --scene build/bc/scene --spp 16 32

``--scene``: a scene directory (``undream run`` leaves one in ``OUT/scene``; the README's
16-condition job's holds clear and snow frames). ``--frames`` per weather (default 3: the first
frames of each weather the sequence holds) are rendered whole with the scene's own texture (or
``--texture``, an ``.npy`` of sRGB values such as a run's ``texture_final.npy``) through the
simulator an attack iteration and the evaluation use
(:class:`undream.sim.mitsuba.MitsubaSimulator`): three untimed renders per frame (kernels,
recordings), then ``--repeats`` renders of each frame in a row with other seeds (the first one or
two after a switch from another weather's frames are slower again: keep ``--repeats`` ≥ 5); the
table gives each frame's median in milliseconds and each weather's median against clear's. Run it
alone: the load average is printed.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="a scene directory (sequence.json, frames/)")
    p.add_argument("--spp", type=int, nargs="+", default=[16, 32])
    p.add_argument("--frames", type=int, default=3, help="frames per weather")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--texture", default=None, help="an .npy of sRGB values (default: the scene's own)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    from undream.render.loading import read_texture_srgb
    from undream.settings import load_local
    from undream.sim.mitsuba import MitsubaSimulator
    from undream.spec import load_sequence
    from undream.variant import mitsuba

    scene = Path(args.scene)
    sequence = load_sequence(scene / "sequence.json")
    by_weather: dict[str, list[int]] = {}
    for f in sequence.frames:
        chosen = by_weather.setdefault(f.environment.weather, [])
        if len(chosen) < args.frames:
            chosen.append(f.index)
    mi = mitsuba(load_local().mi_variant)
    sim = MitsubaSimulator(scene)
    own = scene / "textures" / f"{sequence.texture.name}.exr"
    texture = np.load(args.texture) if args.texture else read_texture_srgb(mi, own)
    print(f"load average before: {os.getloadavg()[0]:.2f}; {scene}: "
          + ", ".join(f"{w} frames {v}" for w, v in by_weather.items()))
    for indices in by_weather.values():
        for index in indices:
            for seed in (1, 2, 3):  # untimed: a frame's first 2–3 renders are slower (kernels, recordings)
                sim.render(index, texture, args.spp[0], seed)
    print("| weather | spp | frame: median ms | weather median ms | against clear |")
    print("|---|---:|---|---:|---:|")
    for spp in args.spp:
        medians: dict[str, float] = {}
        rows = []
        for weather, indices in by_weather.items():
            per_frame = []
            for index in indices:
                times = []
                for k in range(args.repeats):
                    t = time.perf_counter()
                    sim.render(index, texture, spp, 100 + k)
                    times.append(time.perf_counter() - t)
                per_frame.append((index, 1000 * statistics.median(times)))
            medians[weather] = statistics.median(ms for _, ms in per_frame)
            rows.append((weather, per_frame))
        clear = medians.get("clear")
        for weather, per_frame in rows:
            ratio = f"{medians[weather] / clear:.2f}×" if clear else "n/a"
            print(f"| {weather} | {spp} | " + ", ".join(f"{i}: {ms:.1f}" for i, ms in per_frame)
                  + f" | {medians[weather]:.1f} | {ratio} |")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
