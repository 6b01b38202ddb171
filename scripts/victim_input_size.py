#!/usr/bin/env python
"""What a real detector finds, and what it costs, at each input size: a table to pick defaults from.

    .venv/bin/python scripts/victim_input_size.py --config examples/runs/stop_sign_coco_conditions.yaml \\
        --sizes 512 416 320 256 --out build/victim_size

Renders every frame of the run's scene (all its conditions) once, whole, with
the scene's own texture at the run's ``eval_spp`` (kept in ``--out`` as
``frames.npz`` and reused), then judges them with ``coco:centernet@S`` for each
size S: per condition, the frames on which the object is detected (its class at
IoU ≥ 0.5 with its true box, after the score threshold and NMS) and their mean
score; then times, per frame, the prediction and the loss with its backward pass
(the run's loss) at batch sizes ``--batches`` and torch thread counts
``--threads``, and the same with a channels-last input. Prints a table per part
and writes ``input_size.csv`` (``found.csv`` with ``--found-only``); run it alone (the load average is printed).
"""
from __future__ import annotations

import argparse
import csv
import os
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="examples/runs/stop_sign_coco_conditions.yaml")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 416, 320, 256])
    p.add_argument("--batches", type=int, nargs="+", default=[1, 4, 12])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeats", type=int, default=2, help="timed passes per setting (the median is kept)")
    p.add_argument("--held-out", type=Path, help="a folder of held-out conditions' spec files (*.yaml), "
                   "judged the same way (e.g. examples/conditions_stop)")
    p.add_argument("--found-only", action="store_true", help="judge the frames, time nothing")
    p.add_argument("--out", default="build/victim_size")
    return p.parse_args(argv)


def render_all(cfg, out: Path, base_dir: Path) -> tuple[list[np.ndarray], Any]:
    """The run context and every frame rendered whole with the scene's texture (sRGB H×W×3), cached."""
    from scheduler.local import resolve_scene
    from undream.engine.algorithm import render_frames, start_texture
    from undream.engine.context import build_context
    from undream.color import linear_to_srgb

    ctx = build_context(cfg, resolve_scene(cfg, out, base_dir, reuse=True))
    cache = out / "frames.npz"
    if cache.is_file():
        images = list(np.load(cache)["images"])
    else:
        images = [linear_to_srgb(im) for im in render_frames(ctx, start_texture(ctx), None)]
        np.savez_compressed(cache, images=np.stack(images))
    return images, ctx


def found(ctx, victim, images: list[np.ndarray]) -> list[tuple[str, int, int, float]]:
    """Per condition: (name, frames detected, frames where the object is seen, mean top score of its class)."""
    import torch

    from undream.engine.job import ground_truth, stack_images
    from undream.metrics import is_detected

    with torch.no_grad():
        preds = [p for i in range(0, len(images), 8) for p in victim.predict(stack_images(images[i:i + 8]))]
    rows = []
    for cond, positions in ctx.sequence.condition_ranges():
        seen = [p for p in positions if ctx.targets[p].box is not None]
        label = ctx.targets[positions[0]].label
        hits = sum(bool(is_detected(preds[p], ground_truth(ctx.targets[p]), label)) for p in seen)
        scores = [float(np.max(np.asarray(preds[p].scores)[np.asarray(preds[p].labels) == label], initial=0.0))
                  for p in seen]
        rows.append((cond.name, hits, len(seen), statistics.fmean(scores) if scores else 0.0))
    return rows


def timings(ctx, victim, images: list[np.ndarray], batch: int, threads: int, channels_last: bool,
            repeats: int) -> tuple[float, float]:
    """Seconds per frame of the prediction and of the loss with its backward pass (medians)."""
    import torch

    from undream.engine.job import stack_images

    torch.set_num_threads(threads)
    x = stack_images([images[i % len(images)] for i in range(batch)])
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    targets = [ctx.targets[i % len(images)] for i in range(batch)]
    pred_t, loss_t = [], []
    for _ in range(repeats + 1):  # the first pass warms up
        t0 = time.perf_counter()
        with torch.no_grad():
            victim.predict(x)
        t1 = time.perf_counter()
        xg = x.clone().requires_grad_(True)
        losses, _ = victim.loss_and_predict(xg, targets, ctx.config.loss)
        torch.autograd.grad(losses.sum(), xg)
        t2 = time.perf_counter()
        pred_t.append((t1 - t0) / batch)
        loss_t.append((t2 - t1) / batch)
    return statistics.median(pred_t[1:]), statistics.median(loss_t[1:])


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    from undream.spec.run import load_run_config
    from undream.victims import load_victim

    cfg = load_run_config(ROOT / args.config)
    out = ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {os.getloadavg()[0]:.2f}", flush=True)
    images, ctx = render_all(cfg, out, (ROOT / args.config).parent)
    judged = [("attacked", images, ctx)]
    for spec in sorted(args.held_out.glob("*.yaml")) if args.held_out else []:
        held, held_ctx = render_all(replace(cfg, scene=str(spec.resolve()), conditions=None),
                                    out / "held_out" / spec.stem, spec.parent)
        judged.append(("held-out", held, held_ctx))
    base = cfg.victim.partition("@")[0]
    rows = []
    for size in args.sizes:
        victim = load_victim(f"{base}@{size}", task="detection")
        for kind, imgs, c in judged:
            for name, hits, seen, score in found(c, victim, imgs):
                rows.append({"size": size, "part": "found", "kind": kind, "condition": name, "detected": hits,
                             "seen": seen, "mean_score": round(score, 3)})
                print(f"{size:5d}  {kind:9s} {name:44s} detected {hits:3d}/{seen:<3d} mean score {score:.3f}",
                      flush=True)
        for threads in [] if args.found_only else args.threads:
            for batch in args.batches:
                for cl in (False, True):
                    p, l = timings(ctx, victim, images, batch, threads, cl, args.repeats)
                    rows.append({"size": size, "part": "time", "threads": threads, "batch": batch,
                                 "channels_last": cl, "predict_s": round(p, 4), "loss_backward_s": round(l, 4)})
                    print(f"{size:5d}  threads {threads} batch {batch:2d} channels_last {cl!s:5s} "
                          f"predict {p:.3f} s/frame  loss+backward {l:.3f} s/frame", flush=True)
    keys = sorted({k for r in rows for k in r}, key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99)
    table = out / ("found.csv" if args.found_only else "input_size.csv")
    with open(table, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    print(f"load average after: {os.getloadavg()[0]:.2f}; table: {table}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
