"""Benchmark the transport cache against prb's backward pass, per frame of a camera orbit.

    python benchmarks/bench_transport.py --px 64 256 [512] --frames 3 --grad-spp 8

A builtin trash bin (256×256 texture), the camera orbiting it. For each
resolution and frame: the capture time (prb's primal pass with a white
texture on the samples that hit the object + sparse assembly), the
transport's bytes, prb's texture gradient (``texture_gradient``: median of
``--repeats`` after a warm-up), the cached one (``texture_gradient_cached``),
their ratio, and the cached gradient's cosine and relative L2 error against
prb at the same seed and spp (they should agree to float rounding). Medians
over the frames are printed.

The bias question: a cached J keeps one sample pattern (seed_grad) for every
iteration. ``cos(J,ref)`` is the cosine between the cached gradient and a
high-spp prb reference (``--ref-spp``, another seed); ``cos(fresh,ref)`` is
that of a fresh-seed prb gradient at grad_spp. They are about equal: one
cached gradient is as good as one fresh gradient; what a fixed J loses is
that its error does not average out over iterations, which ``cos(Jk,ref)``
vs ``cos(freshk,ref)`` shows (mean of ``--avg`` gradients from ``--avg``
captures vs ``--avg`` fresh seeds: resampling J every few iterations recovers
the averaging).
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
    p.add_argument("--px", type=int, nargs="+", default=[64, 256])
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--grad-spp", type=int, default=8)
    p.add_argument("--ref-spp", type=int, default=256)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--avg", type=int, default=4)
    p.add_argument("--texture", type=int, default=256, help="texture width = height in texels")
    return p.parse_args(argv)


def _scene(px: int, frames: int, texture: int, out: Path) -> Path:
    from undream.scene.trajectory import sequence_from_trajectory
    from undream.scenedir.init import InitOptions, init_scene

    spec = {
        "name": f"bin_orbit_{px}", "seed": 0, "frames": frames, "fps": 2,
        "camera": {"fov": 40, "resolution": [px, px],
                   "path": {"type": "orbit", "center": [0, 0, 0], "radius": 2.6, "height": 1.1,
                            "start_deg": 0, "end_deg": 120},
                   "look_at": "object", "look_at_offset": [0, 0.5, 0]},
        "object": {"asset": {"name": "bin", "mesh": "builtin:trash_bin",
                             "texture": {"resolution": [texture, texture]}},
                   "path": {"type": "static", "position": [0, 0, 0]}},
        "environment": {"weather": "clear", "time_of_day": 15.5, "background": "plain"},
    }
    return init_scene(sequence_from_trajectory(spec), out / f"px{px}", InitOptions(verify_spp=1))


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel().astype(np.float64), b.ravel().astype(np.float64)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-30))


def _timed(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def bench(px: int, args: argparse.Namespace, tmp: Path) -> dict[str, float]:
    from undream.render.differentiable import texture_gradient
    from undream.render.scene_cache import SceneCache
    from undream.render.transport import capture_transport, texture_gradient_cached

    scenes = SceneCache(_scene(px, args.frames, args.texture, tmp), frozen=False)
    rng = np.random.default_rng(px)
    tex = rng.uniform(0.2, 0.8, (args.texture, args.texture, 3)).astype(np.float32)  # sRGB
    spp, rows = args.grad_spp, []
    for index in range(args.frames):
        seed_grad = 1000 + 2 * index
        g = rng.normal(size=(px, px, 3)).astype(np.float32)
        t0 = time.perf_counter()
        tr = capture_transport(scenes, index, spp, seed_grad)
        t_cap = time.perf_counter() - t0

        def prb(seed=seed_grad, n=spp):
            return texture_gradient(scenes, index, tex, g, n, seed + 1, seed)

        t_prb, g_prb = _timed(prb, args.repeats)
        t_vjp, g_j = _timed(lambda: texture_gradient_cached(tr, tex, g), max(args.repeats, 20))
        ref = prb(seed=777_777 + index, n=args.ref_spp)
        fresh = [prb(seed=50_000 + 10 * index + 2 * k) for k in range(args.avg)]
        caps = [g_j] + [texture_gradient_cached(capture_transport(scenes, index, spp, 90_000 + 10 * index + 2 * k),
                                                tex, g) for k in range(1, args.avg)]
        rows.append({
            "capture_s": t_cap, "nbytes": tr.nbytes, "prb_s": t_prb, "cached_s": t_vjp,
            "cos_prb": _cos(g_j, g_prb),
            "rel_prb": float(np.linalg.norm(g_j - g_prb) / np.linalg.norm(g_prb)),
            "cos_J_ref": _cos(g_j, ref), "cos_fresh_ref": _cos(fresh[0], ref),
            "cos_Jk_ref": _cos(np.mean(caps, axis=0), ref), "cos_freshk_ref": _cos(np.mean(fresh, axis=0), ref),
        })
    scenes.close()
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    med["first_capture_s"] = rows[0]["capture_s"]
    return med


def main(argv=None) -> None:
    args = _parse(argv)
    from undream.variant import mitsuba

    mi = mitsuba()
    tmp = Path(tempfile.mkdtemp(prefix="undream-bench-transport-"))
    print(f"trash bin orbit, {args.frames} frames, texture {args.texture}², grad_spp {args.grad_spp}, "
          f"reference spp {args.ref_spp}, averages over {args.avg}, variant {mi.variant()}; "
          "medians over frames")
    head = (f"{'px':>5}{'capture s':>10}{'(1st)':>7}{'MB/frame':>9}{'prb s':>8}{'cached s':>10}{'prb/cached':>11}"
            f"{'cos prb':>9}{'rel prb':>9}{'cos(J,ref)':>11}{'cos(fresh,ref)':>15}"
            f"{'cos(Jk,ref)':>12}{'cos(freshk,ref)':>16}")
    print(head, flush=True)
    for px in args.px:
        m = bench(px, args, tmp)
        print(f"{px:>5}{m['capture_s']:>10.3f}{m['first_capture_s']:>7.2f}{m['nbytes'] / 2**20:>9.2f}"
              f"{m['prb_s']:>8.3f}{m['cached_s']:>10.4f}{m['prb_s'] / m['cached_s']:>11.1f}"
              f"{m['cos_prb']:>9.6f}{m['rel_prb']:>9.1e}{m['cos_J_ref']:>11.3f}{m['cos_fresh_ref']:>15.3f}"
              f"{m['cos_Jk_ref']:>12.3f}{m['cos_freshk_ref']:>16.3f}", flush=True)


if __name__ == "__main__":
    main()
