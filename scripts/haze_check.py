#!/usr/bin/env python
"""The ``haze`` integrator against volpath on a scene directory's frames in fog, rain or snow.

    .venv/bin/python scripts/haze_check.py --scene build/bc/scene [--texture build/bc/texture_final.npy] \\
        [--victim bundled:classifier-v3] [--blends 0.25,0.5,1] [--spp 32] [--every 2] [--out build/haze_check]

Writes a twin of ``--scene`` whose frames in a medium hold volpath's form (the medium and its null
sphere, as :func:`undream.scene.mitsuba_scene.scene_dict` describes them; what scene directories held
before ``haze``), then, per weather, over every ``--every``-th frame in a medium, with ``--texture``
(default: the scene's own):

- the milliseconds of a whole-frame render at ``--spp`` (median of 5 after 3 untimed), volpath and
  haze, and a clear frame's with ``path`` where the scene has one;
- the PSNR (sRGB, clipped) of haze against volpath at one seed, beside volpath's own against another
  seed (the noise floor), and the mean difference of the two at 8×``--spp`` (a bias would stay);
- with ``--victim``: ``undream evaluate`` on both twins (``--frames-csv``) of the scene's own
  texture moved ``--blends`` of the way to ``--texture`` (borderline textures flip verdicts on
  noise), and how many frames' verdicts differ (the own texture's verdicts included), beside the
  frames whose verdicts differ between volpath at ``--spp`` and at ``--spp`` + 1 (its own noise).

Run it alone: the load average is printed.
"""
from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", type=Path, required=True, help="a scene directory written with haze")
    p.add_argument("--texture", type=Path, default=None, help="an .npy of sRGB values (default: the scene's own)")
    p.add_argument("--victim", default=None, help="judge both twins with undream evaluate by this victim")
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--every", type=int, default=2, help="every this-many-th frame in a medium")
    p.add_argument("--blends", type=lambda v: [float(x) for x in v.split(",")], default=[0.25, 0.5, 1.0],
                   help="judge the own texture moved this much of the way to --texture (comma-separated)")
    p.add_argument("--out", type=Path, default=ROOT / "build" / "haze_check")
    return p.parse_args(argv)


def volpath_twin(scene: Path, out: Path) -> Path:
    """A copy of ``scene`` under ``out`` whose frames in a medium are written in volpath's form."""
    from undream.scene.layout import frame_xml
    from undream.scene.mitsuba_scene import ScenePaths, scene_dict
    from undream.scene.xml import to_xml
    from undream.spec import load_sequence

    twin = out / f"{scene.name}_volpath"
    if twin.exists():
        shutil.rmtree(twin)
    shutil.copytree(scene, twin)
    seq = load_sequence(scene / "sequence.json")
    for frame in seq.frames:
        d = scene_dict(seq, frame, ScenePaths(".."), "sim")
        if "fog" in d:
            frame_xml(twin, "sim", frame.index).write_text(to_xml(d, {"spp": 64}))
    return twin


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    from undream.color import linear_to_srgb

    x, y = (np.clip(linear_to_srgb(np.clip(v, 0, None)), 0, 1).astype(np.float64) for v in (a, b))
    mse = float(np.mean((x - y) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def own_texture(scene: Path) -> np.ndarray:
    """The scene directory's own texture (sRGB H×W×3)."""
    from undream.render.loading import read_texture_srgb
    from undream.spec import load_sequence
    from undream.variant import mitsuba

    seq = load_sequence(scene / "sequence.json")
    return read_texture_srgb(mitsuba(), scene / "textures" / f"{seq.texture.name}.exr")


def measure(scene: Path, twin: Path, texture: np.ndarray, spp: int, every: int) -> list[dict]:
    """Per frame in a medium (every ``every``-th): the costs, PSNRs and mean difference of the table."""
    from undream.color import srgb_to_linear
    from undream.render.differentiable import render_frozen
    from undream.render.scene_cache import SceneCache
    from undream.spec import load_sequence
    from undream.variant import mitsuba

    mi = mitsuba()
    seq = load_sequence(scene / "sequence.json")
    tensor = mi.TensorXf(srgb_to_linear(texture.astype(np.float32)))
    caches = {"haze": SceneCache(scene, mi), "volpath": SceneCache(twin, mi)}
    medium = [f for f in seq.frames if f.environment.weather in ("fog", "rain", "snow")][::every]
    clear = [f for f in seq.frames if f.environment.weather == "clear"][::every][:len(medium)]

    def render(kind: str, index: int, s: int, seed: int) -> np.ndarray:
        cache = caches[kind]
        return render_frozen(cache, "sim", cache.frame("sim", index, texture=tensor), s, seed)

    def ms(kind: str, index: int) -> float:
        for seed in (1, 2, 3):
            render(kind, index, spp, seed)
        times = []
        for seed in range(10, 15):
            t0 = time.perf_counter()
            render(kind, index, spp, seed)
            times.append(time.perf_counter() - t0)
        return 1000 * statistics.median(times)

    rows = []
    for f in medium:
        i = f.index
        h, v, v2 = render("haze", i, spp, 1), render("volpath", i, spp, 1), render("volpath", i, spp, 2)
        hb, vb = render("haze", i, 8 * spp, 5), render("volpath", i, 8 * spp, 6)
        rows.append({"frame": i, "weather": f.environment.weather, "ms_volpath": ms("volpath", i),
                     "ms_haze": ms("haze", i), "psnr_haze_volpath": psnr(h, v), "psnr_volpath_volpath": psnr(v2, v),
                     "mean_haze_minus_volpath": float(np.mean(hb - vb)), "mean_volpath": float(np.mean(vb))})
        print(rows[-1], flush=True)
    for f in clear:
        rows.append({"frame": f.index, "weather": "clear", "ms_path": ms("haze", f.index)})
        print(rows[-1], flush=True)
    return rows


def verdicts(own: np.ndarray, texture: np.ndarray, scene: Path, twin: Path, victim: str, spp: int, out: Path,
             blends: list[float]) -> list[tuple[float, int, int, int]]:
    """``undream evaluate`` on both twins of the scene's own texture ``own`` moved BLEND of the way to
    ``texture`` (each of ``blends``; the own texture's verdicts come with each), and on the volpath twin
    again at ``spp + 1`` (other samples: the noise floor): per blend (frames, frames whose verdicts
    differ haze against volpath, volpath against volpath at spp + 1)."""
    cli = Path(sys.executable).with_name("undream")
    rows = []
    for blend in blends:
        judged = out / f"texture_blend{blend:g}.npy"
        np.save(judged, np.clip(own + blend * (texture - own), 0, 1).astype(np.float32))
        got = {}
        for name, folder, n in (("haze", scene, spp), ("volpath", twin, spp), ("volpath_more", twin, spp + 1)):
            csv_path = out / f"frames_{name}_blend{blend:g}.csv"
            subprocess.run([str(cli), "evaluate", str(judged), str(folder), "--victim", victim, "--spp", str(n),
                            "--frames-csv", str(csv_path)], check=True, stdout=subprocess.DEVNULL)
            with csv_path.open() as fh:
                got[name] = {r["frame"]: r for r in csv.DictReader(fh)}
        rows.append((blend, len(got["haze"]), _differing(got["haze"], got["volpath"]),
                     _differing(got["volpath_more"], got["volpath"])))
    return rows


def _differing(a: dict[str, dict], b: dict[str, dict]) -> int:
    """How many frames of two ``--frames-csv`` tables (by frame) have a verdict column that differs."""
    keys = [k for k in next(iter(a.values())) if k.endswith(("_label", "_correct", "_detected"))]
    return sum(any(a[f][k] != b[f][k] for k in keys) for f in a)


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {os.getloadavg()[0]:.2f}", flush=True)
    twin = volpath_twin(args.scene, args.out)
    own = own_texture(args.scene)
    texture = np.load(args.texture) if args.texture else own
    rows = measure(args.scene, twin, texture, args.spp, args.every)
    by = {}
    for r in rows:
        by.setdefault(r["weather"], []).append(r)
    clear = statistics.median(r["ms_path"] for r in by.get("clear", [])) if "clear" in by else None
    print(f"\n| weather | frames | volpath ms | haze ms | haze / volpath | haze / clear (path) | PSNR haze vs volpath "
          f"(dB) | PSNR volpath vs volpath (dB) | mean difference at {8 * args.spp} spp |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for weather, rs in by.items():
        if weather == "clear":
            continue
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        against_clear = f"{med('ms_haze') / clear:.2f}" if clear else "—"
        print(f"| {weather} | {len(rs)} | {med('ms_volpath'):.1f} | {med('ms_haze'):.1f} | "
              f"{med('ms_haze') / med('ms_volpath'):.2f} | {against_clear} | {med('psnr_haze_volpath'):.1f} | "
              f"{med('psnr_volpath_volpath'):.1f} | {np.mean([r['mean_haze_minus_volpath'] for r in rs]):+.5f} "
              f"(of {np.mean([r['mean_volpath'] for r in rs]):.3f}) |")
    if clear:
        print(f"clear frames (path): {clear:.1f} ms median over {len(by['clear'])}")
    if args.victim:
        print(f"\n| texture (own + blend × (texture − own)), judged with the own texture | frames | verdicts haze ≠ "
              f"volpath at {args.spp} spp | volpath at {args.spp + 1} ≠ {args.spp} spp (noise) |\n|---|---:|---:|---:|")
        for blend, n, k, floor in verdicts(own, texture, args.scene, twin, args.victim, args.spp, args.out,
                                           args.blends):
            print(f"| blend {blend:g} | {n} | {k} | {floor} |")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
