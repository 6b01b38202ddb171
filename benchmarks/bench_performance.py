"""Iteration cost against sequence length and resolution: wall time vs Dr.Jit kernel time, before vs after.

    python benchmarks/bench_performance.py                       # the full table (about 10 minutes on 2 cores)
    python benchmarks/bench_performance.py --frames 4 8 32 --px 64 --legacy-max-frames 32

Scenes: the trash bin on a camera orbit (clear afternoon, park), N frames at
P×P pixels, texture 128², sim_spp 16, grad_spp 8, the bundled classifier.
For each configuration the per-frame job (simulator render → victim →
gradient render) runs over every frame for a warm-up iteration (loads and
compiles) and then ``--iterations`` timed iterations. Per part, the table
gives the median wall time per frame (the batched job: every frame
rendered, the victim once on the batch, every frame's gradient; each part's
time over the batch divided by its frames) and the Dr.Jit kernel execution
time of the kernels that part launched (``JitFlag.KernelHistory``); the
job's ratio is its wall time over the kernels' time.

``mode``:
- ``after``: today's engine (one loaded scene per group of equal frames,
  frozen simulator render, gradients from the captured transport, captured
  in the warm-up iteration: its cost per frame is the ``capture s`` column,
  paid once every ``transport_refresh`` iterations);
- ``after-prb``: the same with the prb backward pass for the gradient;
- ``legacy``: every frame's scene kept loaded, nothing frozen, prb
  (``SceneCache(share=False, frozen=False)``), the A/B switch;
- ``pinned``: the engine as it was at commit ``--before`` (default a0c7cd2),
  run from a git worktree on the default example with its own benchmark
  (``benchmarks/bench_iteration.py`` of that commit), for the before/after
  ratio of the default example's iteration.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, nargs="+", default=[4, 8, 32, 64], help="frame counts at 64 px")
    p.add_argument("--px", type=int, nargs="+", default=[64, 256, 512], help="resolutions at 8 frames")
    p.add_argument("--iterations", type=int, default=2)
    p.add_argument("--legacy-max-frames", type=int, default=32, help="skip the legacy mode above this")
    p.add_argument("--legacy-max-px", type=int, default=256, help="skip the legacy mode above this")
    p.add_argument("--before", default="a0c7cd2", help="commit of the engine before (pinned run); '' skips")
    p.add_argument("--victim", default="bundled:classifier")
    return p.parse_args(argv)


def orbit_scene(frames: int, px: int, out: Path) -> Path:
    """The trash bin seen from ``frames`` cameras on a full orbit, at ``px``×``px``."""
    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

    seq = Sequence("bench_orbit", Asset("bin", "builtin:trash_bin",
                                        texture=TextureParam(resolution=(128, 128), init=(0.5, 0.5, 0.5))),
                   tuple(Frame(i, Camera(Transform.from_rows(look_at([3.3 * np.sin(a), 1.3, 3.3 * np.cos(a)],
                                                                     [0.0, 0.5, 0.0])), 40.0, (px, px)),
                               Transform.identity(), Environment("clear", 15.5, background="park"))
                         for i, a in enumerate(np.linspace(0, 2 * np.pi, frames, endpoint=False))))
    return init_scene(seq, out, InitOptions(verify_spp=4, force=True))


class KernelClock:
    """Dr.Jit kernel execution seconds launched since the last call."""

    def __init__(self):
        import drjit as dr

        self.dr = dr
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()

    def lap(self) -> float:
        return sum(k.get("execution_time", 0.0) for k in self.dr.kernel_history()) / 1000.0


def measure(scene_dir: Path, mode: str, args, start: int = 1) -> dict[str, float]:
    """Median per-frame seconds of each part (wall and kernels) and the iteration's wall time.

    Iteration 0 is the warm-up; the timed iterations are ``start`` … ``start + iterations − 1``
    (``iteration`` their median, ``iteration_mean`` their mean).
    """
    from undream.engine.algorithm import start_texture as starting_texture
    from undream.engine.context import build_context
    from undream.engine.job import frame_seed, victim_pass
    from undream.color import linear_to_srgb
    from undream.engine.gradient import GradientPath
    from undream.render.differentiable import srgb_encode_grad
    from undream.render.scene_cache import SceneCache
    from undream.sim import make_backend
    from undream.spec.run import RunConfig

    cfg = RunConfig(scene=str(scene_dir), victim=args.victim, loss="ce", sim_spp=16, grad_spp=8,
                    attack={"name": "pgd", "eps": 16, "steps": args.iterations})
    ctx = build_context(cfg, scene_dir)
    if mode == "legacy":
        ctx.scenes.close()
        ctx.scenes = SceneCache(scene_dir, max_loaded=10**6, frozen=False, share=False)
        ctx.sim = make_backend("mitsuba", scene_dir, scenes=ctx.scenes)
    if mode in ("legacy", "after-prb"):
        ctx.gradients = GradientPath(ctx.scenes, "prb")
    tex = starting_texture(ctx)
    clock = KernelClock()
    parts = {k: [] for k in ("sim_wall", "sim_kernel", "victim_wall", "grad_wall", "grad_kernel", "job_wall")}
    iters, first_grad = [], []
    positions = list(range(len(ctx.frame_indices)))
    for k in [0, *range(start, start + args.iterations)]:
        # the batched job (undream.engine.job.render_and_grad_many), each part timed over the batch
        t_iter = time.perf_counter()
        seeds = [frame_seed(cfg.seed, k, index) for index in ctx.frame_indices]
        clock.lap()
        t0 = time.perf_counter()
        lin = [ctx.sim.render(index, tex, cfg.sim_spp, seed) for index, seed in zip(ctx.frame_indices, seeds)]
        srgb = [linear_to_srgb(x) for x in lin]
        t1 = time.perf_counter()
        ks = clock.lap()
        _, g_img, _ = victim_pass(ctx, positions, srgb)
        t2 = time.perf_counter()
        grad_times = []
        for pos, index in enumerate(ctx.frame_indices):
            tg = time.perf_counter()
            ctx.gradients.texture_gradient(index, tex, srgb_encode_grad(lin[pos], g_img[pos]), cfg.grad_spp, k,
                                           seeds[pos])
            grad_times.append(time.perf_counter() - tg)
        t3 = time.perf_counter()
        kg = clock.lap()
        n = len(positions)
        if k == 0:
            first_grad.extend(grad_times)
        if k > 0:  # iteration 0 loads scenes and compiles kernels
            for name, v in zip(parts, ((t1 - t0) / n, ks / n, (t2 - t1) / n, (t3 - t2) / n, kg / n, (t3 - t0) / n)):
                parts[name].append(v)
        if k > 0:
            iters.append(time.perf_counter() - t_iter)
    out = {name: statistics.median(v) for name, v in parts.items()}
    out["iteration"] = statistics.median(iters)
    out["iteration_mean"] = statistics.mean(iters)
    out["loaded"] = ctx.scenes.loaded_count
    out["capture"] = statistics.median(first_grad) if mode == "after" else float("nan")
    out["path"] = ctx.gradients.method(ctx.frame_indices[0])
    ctx.scenes.close()
    return out


def pinned_iteration(commit: str) -> float | None:
    """The default example's median iteration time with the engine of ``commit`` (its own benchmark)."""
    with tempfile.TemporaryDirectory(prefix="undream-pinned-") as tmp:
        wt = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(wt), commit], check=True)
        try:
            env = {**os.environ, "PYTHONPATH": str(wt)}
            res = subprocess.run([sys.executable, "benchmarks/bench_iteration.py", "--scene", "examples/bin_park.yaml",
                                  "--iterations", "3"], cwd=wt, env=env, capture_output=True, text=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(wt)], check=False)
    m = re.search(r"iteration: ([0-9.]+) s median", res.stdout)
    if m is None:
        print(f"pinned run failed:\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}", file=sys.stderr)
        return None
    return float(m.group(1))


def default_example_iteration(args) -> tuple[float, float]:
    """Today's iteration time on examples/bin_park.yaml: the median of 3 iterations without a
    transport capture, and the mean of one refresh period (iterations 5–9: one capture per frame)."""
    from scheduler.local import resolve_scene

    from undream.spec.run import RunConfig

    with tempfile.TemporaryDirectory(prefix="undream-bench-") as tmp:
        cfg = RunConfig(scene="examples/bin_park.yaml")
        scene_dir = resolve_scene(cfg, Path(tmp), ROOT)
        plain = measure(scene_dir, "after", argparse.Namespace(**{**vars(args), "iterations": 3}))
        period = cfg.transport_refresh
        amortised = measure(scene_dir, "after", argparse.Namespace(**{**vars(args), "iterations": period}),
                            start=period)
        return plain["iteration"], amortised["iteration_mean"]


def _row(frames, px, mode, r) -> str:
    return (f"| {frames} | {px} | {mode} | {r['sim_wall']:.4f} | {r['sim_kernel']:.4f} | {r['victim_wall']:.4f} | "
            f"{r['grad_wall']:.4f} | {r['grad_kernel']:.4f} | {r['job_wall']:.4f} | "
            f"{r['job_wall'] / max(r['sim_kernel'] + r['grad_kernel'], 1e-9):.2f} | {r['iteration']:.3f} | "
            f"{r['loaded']} | {r['path']} | {r['capture']:.3f} |")


def main(argv=None) -> None:
    args = _parse(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from undream.variant import mitsuba

    mi = mitsuba()
    load = os.getloadavg()
    print(f"variant {mi.variant()}, {os.cpu_count()} cores, load average before: {load[0]:.2f} {load[1]:.2f}")
    print("| frames | px | mode | sim wall s | sim kernels s | victim s | grad wall s | grad kernels s | "
          "job s | job / kernels | iteration s | scenes loaded | gradient | capture s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    configs = [(n, 64) for n in args.frames] + [(8, p) for p in args.px if p != 64 or 8 not in args.frames]
    with tempfile.TemporaryDirectory(prefix="undream-perf-") as tmp:
        for frames, px in configs:
            scene = orbit_scene(frames, px, Path(tmp) / f"orbit_{frames}_{px}")
            for mode in ("after", "after-prb", "legacy"):
                if mode == "legacy" and (frames > args.legacy_max_frames or px > args.legacy_max_px):
                    continue
                print(_row(frames, px, mode, measure(scene, mode, args)), flush=True)
    if args.before:
        before = pinned_iteration(args.before)
        after, amortised = default_example_iteration(args)
        if before is not None:
            print(f"default example (examples/bin_park.yaml, 8 frames, 64 px), median iteration: "
                  f"commit {args.before} {before:.3f} s, today {after:.3f} s: {before / after:.1f}× faster; "
                  f"today with the transport captured again once per refresh period (mean of iterations 5–9): "
                  f"{amortised:.3f} s: {before / amortised:.1f}× faster")
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f}")


if __name__ == "__main__":
    main()
