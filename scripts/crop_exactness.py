#!/usr/bin/env python
"""What crop rendering changes: composited frames against whole renders, for a run's final texture.

    .venv/bin/python scripts/crop_exactness.py --run build/crop/stop_sign_run [--out build/crop/exactness.csv]

For every frame of the run's scene (``RUN/metadata.json``'s config or ``--config``, the texture
``RUN/texture_final.npy`` or ``--texture``), at the run's ``sim_spp`` and one
iteration's seed:

- ``psnr``: the composited frame (the window rendered on the base) against the
  whole frame rendered with the same texture and seed, in sRGB; ``psnr_noise``:
  two whole renders with different seeds, the noise floor a composite cannot
  beat (its window's samples differ from the whole render's);
- ``leak_max`` / ``leak_px``: outside the window, the largest difference (in
  8-bit sRGB levels) between the whole frame with the final texture and with the
  scene's own texture at the base's seed, and the pixels that differ by more than
  one level: the light of the texture that the composite leaves out;
- the victim's verdicts on the composite and on the whole render: the same or not.

Prints a row per frame and a summary; writes the rows as CSV.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", type=Path, help="an `undream run` output folder")
    p.add_argument("--config", type=Path, help="the run config (default: RUN/metadata.json's)")
    p.add_argument("--texture", type=Path, help="an sRGB H×W×3 .npy (default: RUN/texture_final.npy)")
    p.add_argument("--iteration", type=int, default=7, help="whose seeds the renders use")
    p.add_argument("--every", type=int, default=1, help="every this-many-th frame only")
    p.add_argument("--out", type=Path, help="CSV of the rows (default: RUN/crop_exactness.csv)")
    return p.parse_args(argv)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two sRGB [0, 1] images (inf when equal)."""
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def verdict(record: dict) -> tuple:
    return (record.get("detected"), record.get("label"), record.get("correct"))


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    from scheduler.local import resolve_scene
    from undream.color import linear_to_srgb
    from undream.engine.context import build_context
    from undream.engine.crops import BASE_ITERATION, BASE_SEED
    from undream.engine.job import frame_seed, victim_pass
    from undream.render.differentiable import render_linear
    from undream.spec.run import RunConfig, load_run_config

    if args.run is None and (args.config is None or args.texture is None):
        raise SystemExit("give --run, or both --config and --texture")
    if args.config is not None:
        cfg = load_run_config(args.config)
        base_dir = args.config.resolve().parent
    else:
        cfg = RunConfig.from_json(json.loads((args.run / "metadata.json").read_text())["config"])
        base_dir = Path.cwd()
    texture = np.load(args.texture or args.run / "texture_final.npy").astype(np.float32)
    work = (args.run or ROOT / "build" / "crop") / "exactness"
    scene_dir = args.run / "scene" if args.run is not None and (args.run / "scene").is_dir() \
        else resolve_scene(cfg, work, base_dir, reuse=True)
    ctx = build_context(cfg, scene_dir)
    print(f"load average before: {os.getloadavg()[0]:.2f}", flush=True)
    rows = []
    for pos, index in list(enumerate(ctx.frame_indices))[::args.every]:
        window = ctx.crops.window(index)
        seed = frame_seed(cfg.seed, args.iteration, index)
        whole = linear_to_srgb(render_linear(ctx.scenes, index, texture, cfg.sim_spp, seed))
        other = linear_to_srgb(render_linear(ctx.scenes, index, texture, cfg.sim_spp, seed + 2))
        comp = linear_to_srgb(ctx.crops.render(index, texture, cfg.sim_spp, seed))
        row = {"position": pos, "index": index, "window": "" if window is None else
               f"{window.x0},{window.y0},{window.width}x{window.height}",
               "window_fraction": 1.0 if window is None else round(window.area / (whole.shape[0] * whole.shape[1]), 3),
               "psnr": round(psnr(comp, whole), 2), "psnr_noise": round(psnr(other, whole), 2)}
        if window is not None:
            base_seed = frame_seed(BASE_SEED, BASE_ITERATION, index)
            final = linear_to_srgb(render_linear(ctx.scenes, index, texture, cfg.sim_spp, base_seed))
            base = linear_to_srgb(ctx.crops.base(index, cfg.sim_spp))
            outside = np.ones(whole.shape[:2], bool)
            outside[window.slices] = False
            diff = np.abs(final - base).max(axis=2)[outside] * 255
            row.update(leak_max=round(float(diff.max()), 2), leak_px=int((diff > 1).sum()))
        else:
            row.update(leak_max=0.0, leak_px=0)
        _, _, (r_comp, r_whole) = victim_pass(ctx, [pos, pos], [comp, whole])
        row.update(verdict_same=verdict(r_comp) == verdict(r_whole),
                   score_composite=r_comp.get("score"), score_whole=r_whole.get("score"))
        rows.append(row)
        print("  ".join(f"{k} {v}" for k, v in row.items()), flush=True)
    out = args.out or (args.run or ROOT / "build" / "crop") / "crop_exactness.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    cropped = [r for r in rows if r["window"]]
    print(f"frames {len(rows)}, cropped {len(cropped)}; PSNR composite vs whole: median "
          f"{np.median([r['psnr'] for r in rows]):.2f} dB (two whole renders, other seeds: "
          f"{np.median([r['psnr_noise'] for r in rows]):.2f} dB); outside the window: max "
          f"{max((r['leak_max'] for r in rows), default=0):.2f} levels, "
          f"{sum(r['leak_px'] for r in rows)} px over 1 level; verdicts differ on "
          f"{sum(not r['verdict_same'] for r in rows)} of {len(rows)} frames; "
          f"load average after {os.getloadavg()[0]:.2f}; rows: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
