#!/usr/bin/env python
"""The main job's texture on held-out conditions: runs over seeds, each texture judged on every
condition of examples/conditions/ with `undream evaluate`'s function; prints a table, writes a chart.

    .venv/bin/python scripts/condition_suite.py --out build/conditions [--seeds 0 1 2] [--eps 255] [--steps 100]

For each seed the main job (examples/runs/bin_orbit_pgd.yaml with ``--eps``, ``--steps`` and the
seed) runs in one process; its final texture is then judged by the bundled classifier on every
frame of each condition (examples/conditions/*.yaml: the same trash bin under another background,
weather, light or camera; no run attacks them), and on the attacked scene's own held-out views for
comparison, at the run config's ``eval_spp``. Prints benign and adversarial accuracy per condition,
mean ± standard deviation over the seeds, and writes ``OUT/conditions.csv`` (every seed) and
``OUT/conditions.png``.
"""
from __future__ import annotations

import argparse
import csv
import os
import statistics
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scenes, runs and the results")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--eps", type=float, default=255.0, help="ε in 0–255 sRGB units")
    parser.add_argument("--steps", type=int, default=100)
    args = parser.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from scheduler.evaluate import evaluate, read_texture, run_scene
    from scheduler.local import run_local
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec.run import RunConfig

    start = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    specs = sorted((ROOT / "examples" / "conditions").glob("*.yaml"))
    scenes = {p.stem: init_scene(p, args.out / "scenes" / p.stem, InitOptions(force=True)) for p in specs}
    base = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    rows = []
    for seed in args.seeds:
        config = RunConfig.from_json({**base, "name": f"suite_seed{seed}", "seed": seed,
                                      "scene": str(ROOT / "examples" / "bin_orbit.yaml"),
                                      "attack": {**base["attack"], "eps": args.eps, "steps": args.steps}})
        out = args.out / "runs" / f"seed{seed}"
        run_local(config, out, base_dir=ROOT, progress=False, force=True)
        textures = {f"seed{seed}": (read_texture(out), run_scene(out))}
        judged = evaluate(textures, [out / "scene", *scenes.values()], [base["victim"]], spp=config.eval_spp)
        for row in judged:
            name = Path(row["scene"]).name
            condition = "as attacked (held-out views)" if name == "scene" else name
            if row["split"] == ("held_out" if name == "scene" else "all"):  # own scene: its held-out views
                rows.append({"seed": seed, "condition": condition, "frames": row["frames"],
                             "benign": row["benign"], "adversarial": row["adversarial"]})
        print(f"seed {seed} judged ({time.monotonic() - start:.0f} s)", flush=True)
    _write(args, rows)
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


def _stats(values: list[float]) -> str:
    mean = statistics.fmean(values)
    return f"{mean:.2f} ± {statistics.stdev(values):.2f}" if len(values) > 1 else f"{mean:.2f}"


def _write(args: argparse.Namespace, rows: list[dict]) -> None:
    with open(args.out / "conditions.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    print(f"\nbundled classifier accuracy, PGD ε={args.eps:g}, {args.steps} steps, seeds {args.seeds} "
          "(mean ± standard deviation over seeds)")
    print("| condition | frames | benign | adversarial |")
    print("|---|---|---|---|")
    summary = {}
    for c in conditions:
        mine = [r for r in rows if r["condition"] == c]
        summary[c] = [statistics.fmean(r["adversarial"] for r in mine), statistics.fmean(r["benign"] for r in mine)]
        print(f"| {c} | {mine[0]['frames']} | {_stats([r['benign'] for r in mine])} | "
              f"{_stats([r['adversarial'] for r in mine])} |")
    _chart(args, conditions, summary)


def _chart(args: argparse.Namespace, conditions: list[str], summary: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 3.6), dpi=110)
    xs = range(len(conditions))
    ax.bar([x - 0.2 for x in xs], [summary[c][1] for c in conditions], 0.4, label="benign texture", color="#9bb")
    ax.bar([x + 0.2 for x in xs], [summary[c][0] for c in conditions], 0.4, label="adversarial texture", color="#c44")
    ax.set_xticks(list(xs), [c.replace("_", " ") for c in conditions], rotation=30, ha="right", fontsize=7)
    ax.set_ylim(0, 1)
    ax.set_ylabel("classifier accuracy (0–1)")
    ax.set_title(f"the main job's texture on held-out conditions: PGD ε={args.eps:g}, {args.steps} steps, "
                 f"mean of seeds {args.seeds}", fontsize=8)
    ax.legend(fontsize=7)
    fig.text(0.01, 0.01, f"made by: scripts/condition_suite.py --out {args.out} --seeds "
             f"{' '.join(map(str, args.seeds))} --eps {args.eps:g} --steps {args.steps}", fontsize=6)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(args.out / "conditions.png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
