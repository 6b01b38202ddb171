#!/usr/bin/env python
"""What ``media: auto`` costs and how close it looks: mapped windows against volpath, per weather.

    .venv/bin/undream run examples/runs/bin_orbit_snow.yaml --out build/media_approx/bin_snow_auto
    .venv/bin/python scripts/media_approx.py [--case NAME,SPEC[@WEATHER],TEXTURE,VICTIM,LOSS ...] [--every 3]

For each case (a scene spec with a medium: fog, rain or snow, or ``@WEATHER``
to set one; an attacked sRGB texture ``.npy``: by default the stop sign's of
``examples/runs/stop_sign_main.yaml`` at /tmp/mj/b, and the bin's of the run
above; the victim and its loss), on every ``--every``-th frame, at
``--spp`` samples per pixel, medians of ``--reps`` renders after a warm-up:

- seconds per window (the crop's window, composited on the base) and per whole
  frame: volpath (``media: exact``), the mapped window (``media: auto``), and the
  same spec in clear weather (its own scene, loaded after the medium's is dropped);
  the model's fit, once per frame; ratios to clear;
- inside the window, in sRGB: PSNR and max abs difference (8-bit levels) of the
  mapped frame against the volpath frame of the SAME texture (``exact``: the
  window at the same iteration seed), and against a ``--ref-spp`` volpath
  window (``ref``), beside volpath's own (the ``exact`` frame against ``ref``:
  the noise floor);
- the victim's verdict (the sign found or missed; the classifier right or
  fooled) on the mapped frame, the volpath frame and the whole volpath render,
  of textures on the way from the scene's own to the attacked one (``--blends``:
  own + b × (attacked − own), whose verdicts can differ); the table counts
  agreements over all of them.

Prints a row per frame and a table per case; writes the rows as CSV
(``--out``, default build/media_approx/media_approx.csv).
"""
from __future__ import annotations

import argparse
import csv
import gc
import os
import statistics
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STOP_TEXTURE = "/tmp/mj/b/texture_final.npy"
DEFAULT_CASES = (
    f"stop_fog,examples/conditions_stop/stop_sign_fog.yaml,{STOP_TEXTURE},coco:centernet@256,vanish",
    f"stop_rain,examples/conditions_stop/stop_sign_rain.yaml,{STOP_TEXTURE},coco:centernet@256,vanish",
    "bin_snow,examples/bin_orbit.yaml@snow,build/media_approx/bin_snow_auto/texture_final.npy,"
    "bundled:classifier-v3,ce",
)


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", action="append", help="NAME,SPEC,TEXTURE,VICTIM,LOSS (repeatable; default: "
                   "the stop sign in fog and in rain, the bin in snow)")
    p.add_argument("--every", type=int, default=3, help="every this-many-th frame")
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--ref-spp", type=int, default=128)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--blends", type=lambda v: [float(x) for x in v.split(",")], default=[0.25, 0.5, 1.0],
                   help="the textures judged: own + BLEND × (attacked − own), comma-separated")
    p.add_argument("--out", type=Path, default=ROOT / "build" / "media_approx" / "media_approx.csv")
    return p.parse_args(argv)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def timed(fn, reps: int) -> tuple[float, object]:
    """The median seconds of ``reps`` calls of ``fn(rep)`` after one untimed call, and the last result."""
    out = fn(-1)
    times = []
    for r in range(reps):
        t0 = time.perf_counter()
        out = fn(r)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def weather_spec(spec: Path, weather: str, work: Path) -> Path:
    """``spec`` with ``environment.weather: WEATHER``, written under ``work`` (relative file paths made absolute)."""
    from undream.spec.io import read_yaml
    import yaml

    data = read_yaml(spec)
    data["environment"] = {**data.get("environment", {}), "weather": weather}
    data["name"] = f"{data['name']}_{weather}"
    tex = data.get("object", {}).get("asset", {}).get("texture", {})
    if isinstance(tex.get("init"), str) and not os.path.isabs(tex["init"]):
        tex["init"] = str((spec.parent / tex["init"]).resolve())
    out = work / f"{data['name']}.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def verdict(record: dict) -> str:
    """The victim's verdict first (``found`` / ``missed`` the sign; ``right`` / ``fooled`` a
    classifier), then its score or label."""
    if "detected" in record:
        return f"{'found' if record['detected'] else 'missed'} {record.get('score') or 0:.2f}"
    return f"{'right' if record.get('correct') else 'fooled'} label={record.get('label')}"


def measure_case(name: str, spec: Path, texture_path: Path, victim: str, loss: str, args, work: Path) -> list[dict]:
    from scheduler.local import resolve_scene
    from undream.color import linear_to_srgb
    from undream.engine.context import build_context
    from undream.engine.job import frame_seed, victim_pass
    from undream.render.crop import PAD, composite
    from undream.render.differentiable import render_linear
    from undream.spec.run import RunConfig

    texture = np.load(texture_path).astype(np.float32)
    spp = args.spp

    def config(scene: Path, media: str = "auto") -> RunConfig:
        return RunConfig(scene=str(scene), name=name, victim=victim, loss=loss, holdout="none", sim_spp=spp,
                         media=media, victim_batch=4)

    scene_dir = resolve_scene(config(spec), work / name, ROOT, reuse=True)
    ctx = build_context(config(scene_dir), scene_dir)
    scenes, crops = ctx.scenes, ctx.crops
    own = crops._texture()
    rows = []
    positions = list(enumerate(ctx.frame_indices))[::args.every]
    for pos, index in positions:
        window = crops.window(index)
        if window is None:
            print(f"{name} frame {index}: no window, skipped", flush=True)
            continue
        base = crops.base(index, spp)
        rendered = window.grown(PAD, *base.shape[:2])
        t0 = time.perf_counter()
        model = crops.medium(index, spp)
        t_fit = time.perf_counter() - t0
        seed = frame_seed(0, 7, index)

        def exact_window(r: int) -> np.ndarray:
            return composite(base, window, render_linear(scenes, index, texture, spp, seed, window=rendered),
                             rendered)

        t_exact, exact = timed(exact_window, args.reps)
        t_auto, mapped = timed(lambda r: crops.render(index, texture, spp, seed), args.reps)
        t_whole, whole = timed(lambda r: render_linear(scenes, index, texture, spp, seed), args.reps)
        ref = composite(base, window, render_linear(scenes, index, texture, args.ref_spp, seed + 11,
                                                    window=rendered), rendered)
        s_map, s_exact, s_ref = (linear_to_srgb(x)[window.slices] for x in (mapped, exact, ref))
        images = []
        for blend in args.blends:  # textures on the way from the scene's own to the attacked one
            t = own + blend * (texture - own)
            images += [crops.render(index, t, spp, seed), composite(
                base, window, render_linear(scenes, index, t, spp, seed, window=rendered), rendered),
                whole if blend == 1.0 else render_linear(scenes, index, t, spp, seed)]
        _, _, records = victim_pass(ctx, [pos] * len(images), [linear_to_srgb(x) for x in images])
        rows.append({
            "case": name, "index": index, "window": f"{window.width}x{window.height}",
            "fraction": round(window.area / base.shape[0] / base.shape[1], 3), "gain": " ".join(
                f"{k:.3f}" for k in model.gain) if model is not None else "",
            "fit_s": round(t_fit, 3), "exact_window_s": round(t_exact, 3), "mapped_window_s": round(t_auto, 3),
            "exact_whole_s": round(t_whole, 3),
            "psnr_mapped_exact": round(psnr(s_map, s_exact), 2),
            "maxdiff_mapped_exact": round(float(np.abs(s_map - s_exact).max() * 255), 1),
            "psnr_mapped_ref": round(psnr(s_map, s_ref), 2),
            "maxdiff_mapped_ref": round(float(np.abs(s_map - s_ref).max() * 255), 1),
            "psnr_exact_ref": round(psnr(s_exact, s_ref), 2),
            "maxdiff_exact_ref": round(float(np.abs(s_exact - s_ref).max() * 255), 1),
        })
        for i, blend in enumerate(args.blends):
            rows[-1].update({f"{blend}_{kind}": verdict(records[3 * i + j]) for j, kind in
                             enumerate(("mapped", "exact", "whole"))})
        print("  ".join(f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    victim_model = ctx.victim
    scenes.close()
    del ctx, scenes, crops
    gc.collect()
    clear_dir = resolve_scene(config(weather_spec(spec, "clear", work)), work / f"{name}_clear", ROOT, reuse=True)
    cctx = build_context(config(clear_dir), clear_dir, victim=victim_model)
    for row in rows:
        index = row["index"]
        cctx.crops.base(index, spp)
        seed = frame_seed(0, 7, index)
        row["clear_window_s"] = round(timed(lambda r: cctx.crops.render(index, texture, spp, seed), args.reps)[0], 3)
        row["clear_whole_s"] = round(timed(lambda r: render_linear(cctx.scenes, index, texture, spp, seed),
                                           args.reps)[0], 3)
        print(f"{name} frame {index}: clear window {row['clear_window_s']} s, whole {row['clear_whole_s']} s",
              flush=True)
    cctx.scenes.close()
    del cctx
    gc.collect()
    return rows


def agree(rows: list[dict], a: str, b: str) -> str:
    """How many (frame, blend) verdicts agree between the ``a`` and ``b`` frames, of how many."""
    keys = [k[:-len("_mapped")] for k in rows[0] if k.endswith("_mapped") and k[0].isdigit()]
    same = sum(r[f"{k}_{a}"].split()[0] == r[f"{k}_{b}"].split()[0] for r in rows for k in keys)
    return f"{same}/{len(rows) * len(keys)}"


def summary(rows: list[dict]) -> list[str]:
    med = lambda k: statistics.median(r[k] for r in rows)  # noqa: E731
    clear_w, clear_f = med("clear_window_s"), med("clear_whole_s")
    return [
        f"| {rows[0]['case']} | {len(rows)} | {med('exact_window_s'):.3f} ({med('exact_window_s') / clear_w:.1f}×) | "
        f"{med('mapped_window_s'):.3f} ({med('mapped_window_s') / clear_w:.2f}×) | {clear_w:.3f} | "
        f"{med('exact_whole_s'):.2f} ({med('exact_whole_s') / clear_f:.1f}×) | {clear_f:.2f} | "
        f"{med('mapped_window_s') / clear_f:.2f}× | {med('fit_s'):.2f} | "
        f"{med('psnr_mapped_exact'):.1f} / {med('psnr_exact_ref'):.1f} | {med('psnr_mapped_ref'):.1f} | "
        f"{max(r['maxdiff_mapped_ref'] for r in rows):.0f} / {max(r['maxdiff_exact_ref'] for r in rows):.0f} | "
        f"{agree(rows, 'mapped', 'exact')}, {agree(rows, 'mapped', 'whole')} ({agree(rows, 'exact', 'whole')}) |"]


HEADER = ("| case | frames | window volpath s | window mapped s | window clear s | whole volpath s | "
          "whole clear s | mapped window / clear whole | fit s (once) | PSNR mapped vs volpath / "
          "volpath vs ref (dB) | PSNR mapped vs ref | max diff mapped / volpath vs ref (levels) | "
          "verdict same as volpath window, whole (volpath window as whole) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    work = args.out.parent
    work.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    all_rows, lines = [], []
    for case in args.case or DEFAULT_CASES:
        name, spec, tex, victim, loss = case.split(",")
        spec, _, weather = spec.partition("@")
        spec_path = (ROOT / spec).resolve()
        if weather:
            spec_path = weather_spec(spec_path, weather, work)
        rows = measure_case(name, spec_path, (ROOT / tex).resolve(), victim, loss, args, work)
        all_rows += rows
        lines += summary(rows)
        print(f"load average after {name}: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(all_rows[0]))
        w.writeheader()
        w.writerows(all_rows)
    print(HEADER)
    print("\n".join(lines))
    print(f"rows: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
