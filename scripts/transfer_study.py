#!/usr/bin/env python
"""Transfer across weather: a texture optimised under one weather, judged under the others.

    .venv/bin/python scripts/transfer_study.py --out build/transfer [--eps 50] [--steps 30] [--seed 0]

For each weather W of ``--weathers`` (default clear, cloudy, fog, night) the
default animated example (examples/bin_orbit.yaml) is initialised under W and
attacked with PGD (``undream run``, the run config examples/runs/bin_orbit_pgd.yaml
with ``--eps``, ``--steps`` and ``--seed``); each final 8-bit texture is then
rendered under every weather and the victim judged on the held-out views
(every 4th, never attacked) and on the attacked ones. Prints the matrices
(rows: optimised under, columns: judged under), writes ``OUT/transfer.csv``
and ``OUT/transfer.png``. Everything renders at the run config's ``eval_spp``.
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scenes, runs and the results")
    parser.add_argument("--weathers", nargs="+", default=["clear", "cloudy", "fog", "night"])
    parser.add_argument("--eps", type=float, default=50.0, help="ε in 0–255 sRGB units")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from scheduler.local import run_local
    from undream.engine.context import build_context
    from undream.engine.patch import evaluate_texture
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec.run import RunConfig, split_frames
    from undream.victims import load_victim

    args.out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    spec = yaml.safe_load((ROOT / "examples" / "bin_orbit.yaml").read_text())
    base = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    base.update(seed=args.seed, attack={**base["attack"], "eps": args.eps, "steps": args.steps})
    scenes, textures = {}, {}
    for w in args.weathers:
        spec_w = {**spec, "name": f"bin_orbit_{w}", "environment": {**spec["environment"], "weather": w}}
        scenes[w] = init_scene_from(spec_w, args.out / f"scene_{w}", init_scene, InitOptions(force=True))
        config = RunConfig.from_json({**base, "name": f"transfer_{w}", "scene": str(scenes[w])})
        run_local(config, args.out / f"run_{w}", base_dir=args.out, progress=False, force=True)
        textures[w] = np.load(args.out / f"run_{w}" / "texture_final.npy")
        print(f"optimised under {w} ({time.monotonic() - start:.0f} s)", flush=True)
    victim = load_victim(base["victim"])
    table: dict[tuple[str, str], dict] = {}
    for judged_under in args.weathers:
        config = RunConfig.from_json({**base, "name": "judge", "scene": str(scenes[judged_under])})
        ctx = build_context(config, scenes[judged_under], victim=victim)
        attacked, held = split_frames(config.holdout, len(ctx.sequence.frames))
        splits = {"attacked": attacked, "held_out": held}
        table[("benign", judged_under)] = evaluate_texture(ctx, _start(ctx), splits)
        for optimised_under in args.weathers:
            table[(optimised_under, judged_under)] = evaluate_texture(ctx, textures[optimised_under], splits)
        ctx.scenes.close()
    _write(args, table)
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


def init_scene_from(spec: dict, out: Path, init_scene, options) -> Path:
    path = out.with_suffix(".yaml")
    path.write_text(yaml.safe_dump(spec))
    return init_scene(path, out, options)


def _start(ctx) -> np.ndarray:
    from undream.engine.algorithm import start_texture as starting_texture

    return starting_texture(ctx)


def _write(args: argparse.Namespace, table: dict) -> None:
    rows = ["benign", *args.weathers]
    with open(args.out / "transfer.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["optimised under", "judged under", "split", "metric", "value"])
        for r in rows:
            for c in args.weathers:
                for split, judged in table[(r, c)].items():
                    writer.writerow([r, c, split, judged["metric"], judged["value"]])
    for split in ("held_out", "attacked"):
        print(f"\n{split.replace('_', '-')} views: accuracy (rows: texture optimised under; columns: judged under)")
        print("| optimised under | " + " | ".join(args.weathers) + " |")
        print("|---" * (len(args.weathers) + 1) + "|")
        for r in rows:
            cells = [f"{table[(r, c)][split]['value']:.3f}" for c in args.weathers]
            print(f"| {r} | " + " | ".join(cells) + " |")
    _chart(args, table, rows)


def _chart(args: argparse.Namespace, table: dict, rows: list[str]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.array([[table[(r, c)]["held_out"]["value"] for c in args.weathers] for r in rows])
    fig, ax = plt.subplots(figsize=(5.5, 4.2), dpi=110)
    im = ax.imshow(values, vmin=0, vmax=1, cmap="viridis")
    ax.set_xticks(range(len(args.weathers)), args.weathers)
    ax.set_yticks(range(len(rows)), ["benign texture" if r == "benign" else r for r in rows])
    ax.set_xlabel("judged under (held-out views)")
    ax.set_ylabel("texture optimised under")
    for i in range(len(rows)):
        for j in range(len(args.weathers)):
            ax.text(j, i, f"{values[i, j]:.2f}", ha="center", va="center", color="w" if values[i, j] < 0.6 else "k")
    fig.colorbar(im, ax=ax, label="victim accuracy (0–1)")
    ax.set_title(f"transfer across weather: PGD ε={args.eps:g}, {args.steps} steps, seed {args.seed}", fontsize=9)
    fig.text(0.01, 0.01, f"made by: scripts/transfer_study.py --out {args.out} --eps {args.eps:g} "
             f"--steps {args.steps} --seed {args.seed}", fontsize=6)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(args.out / "transfer.png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
