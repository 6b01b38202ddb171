"""Benchmark one attack iteration: time split, frames per second, job overhead.

Runs the per-frame job (simulator render → victim → gradient render) on every
frame of a scene for a few iterations, then times each part alone on the same
inputs, and prints a table:

    python benchmarks/bench_iteration.py --scene examples/bin_park.yaml --iterations 3

The overhead ratio is (per-frame job time) / (sum of its parts timed alone):
it measures what the job adds around the three heavy calls (conversions,
finite checks, bookkeeping). All ratios come from one run.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="examples/bin_park.yaml", help="scene directory or spec file")
    p.add_argument("--victim", default="bundled:classifier")
    p.add_argument("--loss", default="ce")
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--sim-spp", type=int, default=16)
    p.add_argument("--grad-spp", type=int, default=8)
    return p.parse_args(argv)


def main(argv=None) -> None:
    args = _parse(argv)
    from scheduler.local import resolve_scene
    from undream.engine.algorithm import start_texture as starting_texture
    from undream.engine.context import build_context
    from undream.engine.job import frame_seed, render_and_grad, victim_loss_and_grad
    from undream.color import linear_to_srgb
    from undream.render.differentiable import srgb_encode_grad
    from undream.spec.run import RunConfig

    tmp = Path(tempfile.mkdtemp(prefix="undream-bench-"))
    cfg = RunConfig(scene=args.scene, victim=args.victim, loss=args.loss, sim_spp=args.sim_spp,
                    grad_spp=args.grad_spp, attack={"name": "pgd", "eps": 16, "steps": args.iterations})
    scene_dir = resolve_scene(cfg, tmp, Path.cwd())
    ctx = build_context(cfg, scene_dir)
    tex = starting_texture(ctx)
    n = len(ctx.sequence.frames)
    for pos in range(n):  # compile every frame's kernels once (not timed)
        render_and_grad(ctx, pos, tex, 0)

    job_times, parts = [], {"sim_render": [], "victim": [], "grad_render": []}
    iter_times = []
    for k in range(1, args.iterations + 1):
        t_iter = time.perf_counter()
        for pos in range(n):
            res = render_and_grad(ctx, pos, tex, k)
            job_times.append(res.timings["total"])
        iter_times.append(time.perf_counter() - t_iter)
        for pos in range(n):  # the same work, each part alone
            idx, seed = ctx.frame_indices[pos], frame_seed(cfg.seed, k, ctx.frame_indices[pos])
            t0 = time.perf_counter()
            lin = ctx.sim.render(idx, tex, cfg.sim_spp, seed)
            t1 = time.perf_counter()
            _, g_img, _ = victim_loss_and_grad(ctx, pos, linear_to_srgb(lin))
            t2 = time.perf_counter()
            ctx.gradients.texture_gradient(idx, tex, srgb_encode_grad(lin, g_img), cfg.grad_spp, k, seed)
            t3 = time.perf_counter()
            parts["sim_render"].append(t1 - t0)
            parts["victim"].append(t2 - t1)
            parts["grad_render"].append(t3 - t2)

    med = {k: statistics.median(v) for k, v in parts.items()}
    job = statistics.median(job_times)
    total_parts = sum(med.values())
    print(f"scene {scene_dir.name}: {n} frames, {ctx.sequence.frames[0].camera.resolution} px, "
          f"sim_spp {cfg.sim_spp}, grad_spp {cfg.grad_spp}, victim {cfg.victim}, variant {ctx.scenes.mi.variant()}")
    print(f"{'part':<16}{'median s/frame':>16}{'share':>8}")
    for k, v in med.items():
        print(f"{k:<16}{v:>16.4f}{v / total_parts:>8.1%}")
    print(f"{'sum of parts':<16}{total_parts:>16.4f}")
    print(f"{'per-frame job':<16}{job:>16.4f}")
    print(f"overhead ratio (job / sum of parts alone): {job / total_parts:.3f}")
    it = statistics.median(iter_times)
    print(f"iteration: {it:.3f} s median over {len(iter_times)}; {n / it:.2f} frames/s")


if __name__ == "__main__":
    main()
