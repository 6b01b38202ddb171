"""The same attack driven by Cycles frames and by Mitsuba frames: gradient agreement and cross-evaluation.

    .venv/bin/python scripts/blender_attack_compare.py examples/runs/bin_orbit_pgd_blender.yaml --out /tmp/cmp

1. Gradients: at the starting texture, every attacked frame's texture
   gradient with Cycles frames (``sim: blender``; Mitsuba's gradient scene
   carries it to the texture) against the all-Mitsuba gradient at the same
   iteration and seeds: per-frame cosine and the cosine of their sums (what
   the attack's step uses); the noise floor is the all-Mitsuba gradient at
   two different seeds.
2. Runs: the run config as given (``sim: blender``) and the same with
   ``sim: mitsuba`` (same attack, budget and seed), each written under
   ``--out``; then every final texture evaluated in both simulators
   (accuracy over all frames, attacked and held-out apart).

Prints JSON lines and a Markdown table; writes ``--out/compare.json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from scheduler.local import run_local
from undream.engine.context import build_context
from undream.engine.algorithm import predict, quantise, render_frames
from undream.engine.job import render_and_grad
from undream.spec.run import load_run_config, split_frames


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel().astype(np.float64), b.ravel().astype(np.float64)
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30))


def gradients(cfg, scene: Path) -> dict:
    """Per-frame and summed gradient cosines, Cycles-driven vs all-Mitsuba (and Mitsuba vs itself)."""
    mit = build_context(dataclasses.replace(cfg, sim="mitsuba"), scene)
    cyc = build_context(dataclasses.replace(cfg, sim="blender"), scene, victim=mit.victim, scenes=mit.scenes)
    tex = np.full(mit.sequence.texture.shape, 0.5, np.float32)
    attacked, _ = split_frames(cfg.holdout, len(mit.sequence.frames))
    per, per_noise, sums = [], [], {"cyc": 0.0, "mit": 0.0, "mit2": 0.0}
    for p in attacked:
        g_m = render_and_grad(mit, p, tex, 0).grad
        g_c = render_and_grad(cyc, p, tex, 0).grad
        g_m2 = render_and_grad(mit, p, tex, 1).grad  # other seeds: Mitsuba's own noise floor
        per.append(_cos(g_c, g_m))
        per_noise.append(_cos(g_m2, g_m))
        sums = {"cyc": sums["cyc"] + g_c, "mit": sums["mit"] + g_m, "mit2": sums["mit2"] + g_m2}
    cyc.sim.close()
    return {"frames": len(attacked), "cos_per_frame_mean": float(np.mean(per)), "cos_per_frame_min": float(np.min(per)),
            "cos_sum": _cos(sums["cyc"], sums["mit"]),
            "noise_floor_per_frame_mean": float(np.mean(per_noise)), "noise_floor_sum": _cos(sums["mit2"], sums["mit"])}


def cross_evaluate(cfg, scene: Path, texture: np.ndarray) -> dict:
    """Accuracy of the victim on ``texture`` (8-bit quantised) rendered by each simulator."""
    out = {}
    victim = None
    for sim in ("mitsuba", "blender"):
        ctx = build_context(dataclasses.replace(cfg, sim=sim), scene, victim=victim)
        victim = ctx.victim
        preds = predict(ctx, render_frames(ctx, quantise(texture), None))
        label = ctx.targets[0].label
        ok = np.array([int(p.label) == label for p in preds])
        attacked, held = split_frames(cfg.holdout, len(preds))
        out[sim] = {"all": float(ok.mean()), "attacked": float(ok[attacked].mean()),
                    "held_out": float(ok[held].mean()) if held else None}
        if sim == "blender":
            ctx.sim.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    cfg = load_run_config(args.run)
    results: dict = {"config": cfg.to_json()}
    runs = {}
    for sim in ("blender", "mitsuba"):
        c = dataclasses.replace(cfg, sim=sim)
        t0 = time.perf_counter()
        res = run_local(c, args.out / sim, base_dir=args.run.parent, progress=False, force=True)
        runs[sim] = {"seconds": round(time.perf_counter() - t0, 1),
                     "benign": res["benign"]["value"], "adversarial": res["adversarial"]["value"],
                     "loss_first": res["loss_per_iteration"][0], "loss_last": res["loss_per_iteration"][-1],
                     "wall_time_seconds": res.get("wall_time_seconds")}
        print(json.dumps({"run": sim, **runs[sim]}), flush=True)
    results["runs"] = runs
    scene = args.out / "blender" / "scene"
    if not (scene / "sequence.json").is_file():
        scene = (args.run.parent / cfg.scene).resolve()
    results["gradients"] = gradients(cfg, scene)
    print(json.dumps({"gradients": results["gradients"]}), flush=True)
    benign = np.full(np.load(args.out / "blender" / "texture_final.npy").shape, 0.5, np.float32)
    results["evaluation"] = {"benign": cross_evaluate(cfg, scene, benign)}
    for sim in ("blender", "mitsuba"):
        tex = np.load(args.out / sim / "texture_final.npy")
        results["evaluation"][f"attacked with {sim} frames"] = cross_evaluate(cfg, scene, tex)
    print(json.dumps({"evaluation": results["evaluation"]}), flush=True)
    (args.out / "compare.json").write_text(json.dumps(results, indent=2, default=str))
    print("\n| texture | accuracy in Mitsuba (all / attacked / held out) | accuracy in Cycles (all / attacked / held out) |")
    print("|---|---|---|")
    for name, ev in results["evaluation"].items():
        cells = [f"{ev[s]['all']:.3f} / {ev[s]['attacked']:.3f} / "
                 f"{'n/a' if ev[s]['held_out'] is None else format(ev[s]['held_out'], '.3f')}"
                 for s in ("mitsuba", "blender")]
        print(f"| {name} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
