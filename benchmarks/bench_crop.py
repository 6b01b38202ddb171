#!/usr/bin/env python
"""One attack iteration at 256 px against a real detector, whole frames against crop rendering.

    .venv/bin/python benchmarks/bench_crop.py --frames 18 --iterations 3

The scene of ``--config`` (default: the stop sign in 8 conditions, 256 px,
``coco:centernet``), ``--frames`` of its attacked frames spread over the
conditions, each iteration rendered, judged and carried back to the texture
(:func:`undream.engine.job.render_and_grad_many`, the farm's per-frame job) in
every setting: ``crop: off`` with the victim at its package's 512² input (the
engine before crop rendering: ``crop: off`` takes the code path it had), crop
rendering, crop rendering with the victim's batches at most 4 frames
(``victim_batch: 4``), the victim at 256² (``coco:centernet@256``: a 256-px frame
unresized), both, and both with two torch threads. One iteration per setting in turn,
``--iterations`` rounds after a first untimed one (compiling kernels, rendering
the bases, capturing the transports); the table gives the median seconds per
iteration, per component (summed over the frames) and the speed-up over the
first setting, all from this one run. Run it alone: the load average is printed.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("sim_render", "victim", "grad_render")


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="examples/runs/stop_sign_coco_conditions.yaml")
    p.add_argument("--frames", type=int, default=18)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--out", default="build/bench_crop", help="where the scene is initialised (reused)")
    return p.parse_args(argv)


def settings(victim: str) -> list[tuple[str, dict]]:
    """(label, RunConfig fields) per setting, the engine before crop rendering first."""
    small = f"{victim.partition('@')[0]}@256"
    return [("whole frames, victim 512 (before)", {"crop": "off", "victim": victim}),
            ("crop", {"crop": "auto", "victim": victim}),
            ("crop, victim 512 in batches of 4", {"crop": "auto", "victim": victim, "victim_batch": 4}),
            ("whole frames, victim 256", {"crop": "off", "victim": small}),
            ("crop + victim 256", {"crop": "auto", "victim": small}),
            ("crop + victim 256, 2 threads", {"crop": "auto", "victim": small, "torch_threads": 2})]


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    import torch

    from scheduler.local import resolve_scene
    from undream.engine.algorithm import start_texture
    from undream.engine.context import build_context
    from undream.engine.job import render_and_grad_many
    from undream.render.scene_cache import SceneCache
    from undream.spec.run import load_run_config

    cfg = load_run_config(ROOT / args.config)
    scene_dir = resolve_scene(cfg, ROOT / args.out, (ROOT / args.config).parent, reuse=True)
    scenes = SceneCache(scene_dir)
    contexts = [(label, build_context(replace(cfg, **fields), scene_dir, scenes=scenes))
                for label, fields in settings(cfg.victim)]
    attacked = cfg.split(contexts[0][1].sequence).attacked
    step = max(1, len(attacked) // args.frames)
    positions = list(attacked[::step][:args.frames])
    texture = start_texture(contexts[0][1])
    print(f"load average before: {os.getloadavg()[0]:.2f}; {len(positions)} frames of {scene_dir}", flush=True)
    times: dict[str, list[float]] = {label: [] for label, _ in contexts}
    parts: dict[str, dict[str, list[float]]] = {label: {p: [] for p in PARTS} for label, _ in contexts}
    for k in range(args.iterations + 1):
        for label, ctx in contexts:
            torch.set_num_threads(ctx.config.torch_threads)
            t0 = time.perf_counter()
            results = render_and_grad_many(ctx, positions, texture, k)
            wall = time.perf_counter() - t0
            if k == 0:
                continue
            times[label].append(wall)
            for p in PARTS:
                parts[label][p].append(sum(r.timings[p] for r in results))
        print(f"iteration {k} done", flush=True)
    first = statistics.median(times[contexts[0][0]])
    print(f"\n{'setting':<34}{'iteration s':>12}{'sim':>8}{'victim':>8}{'grad':>8}{'speed-up':>10}")
    for label, _ in contexts:
        it = statistics.median(times[label])
        med = [statistics.median(parts[label][p]) for p in PARTS]
        print(f"{label:<34}{it:>12.2f}" + "".join(f"{v:>8.2f}" for v in med) + f"{first / it:>9.2f}×")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
