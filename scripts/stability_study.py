#!/usr/bin/env python
"""Stability where methods fail: what the gradients and the results do in the hard cases.

    .venv/bin/python scripts/stability_study.py --out build/stability [--eps 50] [--steps 20] [--seeds 0 1]

Every case is an 8-frame variant of the default animated example (the trash
bin seen all around, every 4th frame held out), attacked with PGD at ``--eps``
for ``--steps`` iterations (``undream run``) for each seed of ``--seeds``:

- ``reference``: the bin orbit itself;
- ``pitch_down_90``: the camera straight above the bin (pitch −90°: the view
  direction is parallel to the world's up axis), the bin turning under it;
- ``pitch_up_90``: the camera straight below a floating bin (pitch +90°);
- ``grazing``: a stop sign seen 70° → 88° off its normal;
- ``tiny``: the orbit at 30 m, where the bin covers a few pixels;
- ``night``: the night preset (street lights, dim sky);
- ``occluded``: a parked van (the built-in car, 1.4 m tall) between the camera
  and the bin for part of the orbit;
- ``saturated``: a white starting texture at ε = 255 (texels start at the
  bound; bright pixels clip, which passes no gradient);
- ``flat_ce`` / ``flat_dlr``: the bundled classifier with its logits × 1000
  (softmax saturated: cross-entropy's gradient underflows), attacked with
  cross-entropy and with the scale-invariant DLR loss.

Records per run: the object's visible pixels (from the scene's masks), benign
and adversarial accuracy on the attacked and held-out views, the texture
gradient's norm per iteration, frames dropped as non-finite, the fraction of
texel channels at 0 or 1 at the end, and the error of a run that failed
(failures are rows of the table, not hidden). Writes ``OUT/stability.csv``,
``OUT/stability_grad_norm.png`` (gradient norm against iteration per case) and
``OUT/stability_frames.png`` (per case: the first attacked frame, benign and
adversarial, with the prediction), and prints the table.
"""
from __future__ import annotations

import argparse
import copy
import csv
import json
import os
import shutil
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
FLAT_SCALE = 1000.0  # logits × this: the "flat gradient" victim


def _base_spec() -> dict:
    spec = yaml.safe_load((ROOT / "examples" / "bin_orbit.yaml").read_text())
    spec["frames"] = 8
    spec["camera"]["path"] = {**spec["camera"]["path"], "end_deg": 315}
    return spec


def _turning(position: list[float]) -> dict:
    """The object at ``position``, turning once around its vertical axis over the 8 frames."""
    keys = [{"frame": f, "position": position, "yaw": y} for f, y in ((0, 0), (2, 90), (4, 180), (6, 270), (7, 315))]
    return {"type": "keyframes", "interpolation": "linear", "keys": keys}


def cases(victim_flat: str) -> dict[str, tuple[dict, dict]]:
    """name → (scene spec, run-config overrides)."""
    base = _base_spec()
    out: dict[str, tuple[dict, dict]] = {"reference": (base, {})}

    s = copy.deepcopy(base)
    s["camera"]["path"] = {"type": "static", "position": [0, 4.0, 0]}
    s["object"]["path"] = _turning([0, 0, 0])
    out["pitch_down_90"] = (s, {})

    s = copy.deepcopy(base)
    s["camera"]["path"] = {"type": "static", "position": [0, 0.3, 0]}
    s["camera"]["look_at_offset"] = [0, 0, 0]
    s["object"]["path"] = _turning([0, 2.5, 0])
    out["pitch_up_90"] = (s, {})

    s = copy.deepcopy(base)
    ang = np.radians([70.0, 88.0])
    s["camera"]["path"] = {"type": "keyframes", "interpolation": "linear", "keys": [
        {"frame": 0, "position": [float(4 * np.sin(ang[0])), 1.8, float(4 * np.cos(ang[0]))], "look_at": [0, 1.8, 0]},
        {"frame": 7, "position": [float(4 * np.sin(ang[1])), 1.8, float(4 * np.cos(ang[1]))], "look_at": [0, 1.8, 0]}]}
    s["camera"].pop("look_at", None)
    s["camera"].pop("look_at_offset", None)
    s["object"] = {"asset": {"name": "sign", "mesh": "builtin:stop_sign", "texture": {"resolution": [128, 128]}},
                   "path": {"type": "static", "position": [0, 0, 0]}}
    s["environment"] = {**s["environment"], "background": "street"}
    out["grazing"] = (s, {})

    s = copy.deepcopy(base)
    s["camera"]["path"] = {**s["camera"]["path"], "radius": 30.0, "height": 2.0}
    out["tiny"] = (s, {})

    s = copy.deepcopy(base)
    s["environment"] = {**s["environment"], "weather": "night"}
    out["night"] = (s, {})

    s = copy.deepcopy(base)
    s["actors"] = [{"asset": {"name": "van", "mesh": "builtin:car", "color": [0.6, 0.6, 0.62]},
                    "path": {"type": "static", "position": [0, 0, 1.9]}, "yaw": 90}]
    out["occluded"] = (s, {})

    s = copy.deepcopy(base)
    s["object"]["asset"]["texture"] = {**s["object"]["asset"]["texture"], "init": [1.0, 1.0, 1.0]}
    out["saturated"] = (s, {"attack.eps": 255})

    out["flat_ce"] = (base, {"victim": victim_flat, "loss": "ce"})
    out["flat_dlr"] = (base, {"victim": victim_flat, "loss": "dlr"})
    return out


def flat_victim(out: Path) -> Path:
    """The bundled classifier with its logits × FLAT_SCALE: same predictions, a saturated softmax."""
    from safetensors.numpy import load_file, save_file

    from undream.victims.registry import bundled_path

    src = bundled_path("classifier")
    if (out / "model.safetensors").is_file():
        return out
    shutil.copytree(src, out, dirs_exist_ok=True)
    weights = load_file(str(src / "model.safetensors"))
    for key in ("classifier.1.weight", "classifier.1.bias"):
        weights[key] = (weights[key] * FLAT_SCALE).astype(np.float32)
    save_file(weights, str(out / "model.safetensors"), metadata={"format": "pt"})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scenes, runs and the results")
    parser.add_argument("--eps", type=float, default=50.0, help="ε in 0–255 sRGB units")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--only", nargs="+", help="case names to run (default: all)")
    parser.add_argument("--reuse", action="store_true", help="keep runs that finished earlier under OUT")
    args = parser.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from scheduler.local import run_local
    from scheduler.sweep import set_dotted
    from undream.errors import UndreamError
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec.run import RunConfig

    args.out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    base_run = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    base_run.update(attack={**base_run["attack"], "eps": args.eps, "steps": args.steps})
    all_cases = cases(str(flat_victim(args.out / "victim_flat")))
    rows, pictures = [], []
    for name, (spec, overrides) in all_cases.items():
        if args.only and name not in args.only:
            continue
        scene = args.out / "scenes" / name
        spec_path = args.out / "scenes" / f"{name}.yaml"
        spec_path.parent.mkdir(parents=True, exist_ok=True)
        spec_path.write_text(yaml.safe_dump({**spec, "name": name}))
        try:
            if not (scene / "sequence.json").is_file():
                init_scene(spec_path, scene, InitOptions(force=True, progress=False))
        except UndreamError as err:
            rows.append({"case": name, "seed": "", "error": f"init: {err}"})
            print(f"{name}: init failed: {err}", flush=True)
            continue
        visible = _visible_pixels(scene)
        for seed in args.seeds:
            out = args.out / "runs" / f"{name}_s{seed}"
            d = {**base_run, "seed": seed, "scene": str(scene), "name": f"{name}-s{seed}".replace("_", "-")}
            for key, value in overrides.items():
                set_dotted(d, key, value, f"case {name}")
            row = {"case": name, "seed": seed, "visible_px_mean": round(float(np.mean(visible)), 1),
                   "visible_px_min": int(np.min(visible)), "eps": d["attack"]["eps"], "loss": d["loss"]}
            try:
                if not (args.reuse and (out / "results.json").is_file()):
                    run_local(RunConfig.from_json(d), out, base_dir=ROOT, progress=False, force=True)
                row.update(_measure(out))
                if seed == args.seeds[0]:
                    pictures.append((name, out, visible))
            except Exception as err:  # a failure is a result here: recorded, the study goes on
                row["error"] = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
                traceback.print_exc(limit=2)
            rows.append(row)
            print(f"{name} seed {seed}: " + ", ".join(f"{k}={v}" for k, v in row.items() if k not in ("case", "seed")
                                                        and k != "grad_norms")
                  + f" ({time.monotonic() - start:.0f} s, load {os.getloadavg()[0]:.1f})", flush=True)
    _write(args, rows, pictures)
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


def _visible_pixels(scene: Path) -> list[int]:
    from PIL import Image

    from undream.scene.layout import mask_png
    from undream.spec.io import load_sequence

    seq = load_sequence(scene / "sequence.json")
    return [int((np.asarray(Image.open(mask_png(scene, f.index))) > 127).sum()) for f in seq.frames]


def _measure(run: Path) -> dict:
    from undream.store import open_store

    res = json.loads((run / "results.json").read_text())
    store = open_store(None, run / "store")
    try:
        norms = [r.grad_norm for r in store.iterations(res["run_id"])]
    finally:
        store.close()
    tex = np.load(run / "texture_final.npy").astype(np.float32)
    tex = tex / 255.0 if tex.max() > 1.0 else tex

    def value(split: str, kind: str):
        return None if res.get(split) is None else res[split][kind]["value"]

    return {"benign_attacked": value("attacked", "benign"), "adv_attacked": value("attacked", "adversarial"),
            "benign_held_out": value("held_out", "benign"), "adv_held_out": value("held_out", "adversarial"),
            "grad_norm_first": norms[0] if norms else None, "grad_norm_last": norms[-1] if norms else None,
            "grad_norms": norms, "frames_dropped": int(sum(res["frames_dropped_per_iteration"])),
            "loss_first": round(res["loss_per_iteration"][0], 4), "loss_last": round(res["loss_per_iteration"][-1], 4),
            "texels_at_bound": round(float(np.mean((tex <= 0.0) | (tex >= 1.0))), 3), "error": ""}


COLUMNS = ["case", "seed", "visible_px_mean", "visible_px_min", "eps", "loss", "benign_attacked", "adv_attacked",
           "benign_held_out", "adv_held_out", "grad_norm_first", "grad_norm_last", "frames_dropped",
           "loss_first", "loss_last", "texels_at_bound", "error"]


def _write(args: argparse.Namespace, rows: list[dict], pictures: list[tuple[str, Path, list[int]]]) -> None:
    with open(args.out / "stability.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nPGD ε={args.eps:g} (saturated: 255), {args.steps} steps; mean over seeds {args.seeds} "
          "(± std where seeds differ)")
    print("| case | visible px (mean, min) | benign acc. attacked / held-out | adversarial acc. attacked / held-out "
          "| grad norm first → last | frames dropped | texels at 0 or 1 | error |")
    print("|---|---|---|---|---|---|---|---|")
    for name in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == name]
        ok = [r for r in rs if not r.get("error")]
        errors = "; ".join(sorted({r["error"] for r in rs if r.get("error")}))
        if not ok:
            print(f"| {name} | | | | | | | {errors} |")
            continue
        vis = f"{ok[0]['visible_px_mean']:.0f}, {ok[0]['visible_px_min']}"
        print(f"| {name} | {vis} | {_ms(ok, 'benign_attacked')} / {_ms(ok, 'benign_held_out')} | "
              f"{_ms(ok, 'adv_attacked')} / {_ms(ok, 'adv_held_out')} | {_ms(ok, 'grad_norm_first', '.2e')} → "
              f"{_ms(ok, 'grad_norm_last', '.2e')} | {sum(r['frames_dropped'] for r in ok)} | "
              f"{_ms(ok, 'texels_at_bound')} | {errors} |")
    _charts(args, rows, pictures)


def _ms(rows: list[dict], key: str, fmt: str = ".3f") -> str:
    vals = [r[key] for r in rows if r.get(key) is not None]
    if not vals:
        return "–"
    m, s = float(np.mean(vals)), float(np.std(vals))
    return f"{m:{fmt}}" if s == 0 or len(vals) == 1 else f"{m:{fmt}} ± {s:{fmt}}"


def _command(args: argparse.Namespace) -> str:
    return (f"made by: .venv/bin/python scripts/stability_study.py --out {args.out} --eps {args.eps:g} "
            f"--steps {args.steps} --seeds {' '.join(map(str, args.seeds))}")


def _charts(args: argparse.Namespace, rows: list[dict], pictures: list[tuple[str, Path, list[int]]]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    fig, ax = plt.subplots(figsize=(8, 4.6), dpi=110)
    for i, name in enumerate(dict.fromkeys(r["case"] for r in rows)):
        for r in rows:
            if r["case"] == name and r.get("grad_norms"):
                norms = np.maximum(np.array(r["grad_norms"], float), 1e-30)
                ax.plot(range(len(norms)), norms, color=plt.cm.tab10(i % 10), lw=1,
                        label=name if r["seed"] == args.seeds[0] else None)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("texture gradient norm (sum over the step's frames;\nexactly 0 drawn at 1e-30)", fontsize=8)
    ax.set_title(f"stability: gradient norm per case, PGD ε={args.eps:g}, one line per seed", fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.text(0.01, 0.01, _command(args), fontsize=6)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(args.out / "stability_grad_norm.png")
    plt.close(fig)

    if not pictures:
        return
    fig, axes = plt.subplots(2, len(pictures), figsize=(1.6 * len(pictures), 4.0), dpi=110, squeeze=False)
    for j, (name, run, visible) in enumerate(pictures):
        res = json.loads((run / "results.json").read_text())
        frames = res["attacked"]["frames"]
        # The attacked frame showing the least of the object while still showing some (occlusion shows).
        seen = [f for f in frames if visible[f] > 0]
        frame = min(seen, key=lambda f: visible[f]) if seen else frames[0]
        for i, kind in enumerate(("benign", "adversarial")):
            ax = axes[i, j]
            ax.imshow(Image.open(run / f"frames_{kind}" / f"frame_{frame:04d}.png"), interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=7)
            if j == 0:
                ax.set_ylabel(kind, fontsize=7)
    fig.suptitle("per case (seed 0), the attacked frame showing the least of the object: benign (top) and "
                 "adversarial (bottom)", fontsize=8)
    fig.text(0.01, 0.01, _command(args), fontsize=5)
    fig.tight_layout(rect=(0, 0.03, 1, 0.95))
    fig.savefig(args.out / "stability_frames.png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
