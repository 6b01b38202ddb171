#!/usr/bin/env python
"""Textures on held-out conditions: runs over seeds, each texture judged on every condition of
examples/conditions/ with `undream evaluate`'s function; prints a table, writes a chart.

    .venv/bin/python scripts/condition_suite.py --out build/conditions [--seeds 0 1 2] [--eps 255] [--steps 100]
        [--runs examples/runs/bin_orbit_pgd.yaml examples/runs/bin_orbit_conditions.yaml] [--victim V]

For each run config (default: the main job, examples/runs/bin_orbit_pgd.yaml) and seed, the run
(with ``--eps``, ``--steps`` and the seed; ``--victim`` replaces its victim) runs in one process;
its final texture is then judged by the run's victim on every frame of each condition
(examples/conditions/*.yaml: the same trash bin under another background, weather, light or
camera; no run attacks them), and on the attacked scene's own held-out views for comparison, at
the run config's ``eval_spp``. Prints benign and adversarial accuracy per condition and run,
mean ± standard deviation over the seeds, and writes ``OUT/conditions_eps<ε>.csv`` (every seed
and run, with each run's wall time) and ``OUT/conditions_eps<ε>.png``. Runs already finished in
``OUT/runs`` (a ``results.json`` of the same config) are judged again, not run again.
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
    parser.add_argument("--runs", type=Path, nargs="+", default=[ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml"],
                        help="run configs (each one method)")
    parser.add_argument("--victim", default=None, help="the victim of every run and judgement (default: the runs')")
    args = parser.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from undream.cli.options import local_settings

    local_settings()  # Mitsuba's variant and Dr.Jit's pool ($UNDREAM_DRJIT_THREADS), as the commands set them
    from scheduler.evaluate import evaluate, read_texture, run_scene
    from scheduler.local import run_local
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec.run import RunConfig

    start = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    specs = sorted((ROOT / "examples" / "conditions").glob("*.yaml"))
    scenes = {p.stem: init_scene(p, args.out / "scenes" / p.stem, InitOptions(force=True)) for p in specs}
    rows = []
    for run_yaml in args.runs:
        base = yaml.safe_load(run_yaml.read_text())
        victim = args.victim or base["victim"]
        for seed in args.seeds:
            data = {**base, "name": f"{base['name']}_seed{seed}", "seed": seed, "victim": victim,
                    "scene": str((run_yaml.parent / base["scene"]).resolve()),
                    "attack": {**base["attack"], "eps": args.eps, "steps": args.steps}}
            if base.get("conditions"):
                data["conditions"] = {**base["conditions"], "scenes": [
                    str((run_yaml.parent / s).resolve()) for s in base["conditions"].get("scenes", [])]}
            config = RunConfig.from_json(data)
            out = args.out / "runs" / f"{base['name']}_seed{seed}"
            wall = run_once(config, out, run_local)
            textures = {f"seed{seed}": (read_texture(out), run_scene(out))}
            judged = evaluate(textures, [out / "scene", *scenes.values()], [victim], spp=config.eval_spp)
            for row in judged:
                name = Path(row["scene"]).name
                condition = "as attacked (held-out views)" if name == "scene" else name
                if row["split"] == ("held_out" if name == "scene" else "all"):  # own scene: its held-out views
                    rows.append({"run": base["name"], "seed": seed, "condition": condition, "frames": row["frames"],
                                 "benign": row["benign"], "adversarial": row["adversarial"], "run_wall_s": wall})
            print(f"{base['name']} seed {seed} judged ({time.monotonic() - start:.0f} s)", flush=True)
    _write(args, rows)
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


def run_once(config, out: Path, run_local) -> float:
    """Run ``config`` into ``out`` unless a finished run of the same config is there; its wall time (s)."""
    import json

    done = out / "results.json"
    if done.is_file() and json.loads((out / "metadata.json").read_text())["config"] == config.to_json():
        return json.loads(done.read_text())["wall_time_seconds"]["wall"]
    return run_local(config, out, base_dir=ROOT, progress=False, force=True)["wall_time_seconds"]["wall"]


def victim_slug(victim: str) -> str:
    """The victim spec as the studies name their folders and files (``bundled:classifier-v3`` →
    ``bundled_classifier-v3``; a path's separators too)."""
    return victim.replace(":", "_").replace("/", "_")


def mean_sd(values: list[float]) -> str:
    mean = statistics.fmean(values)
    return f"{mean:.2f} ± {statistics.stdev(values):.2f}" if len(values) > 1 else f"{mean:.2f}"


def _write(args: argparse.Namespace, rows: list[dict]) -> None:
    with open(args.out / f"conditions_eps{args.eps:g}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    runs = list(dict.fromkeys(r["run"] for r in rows))
    victim = args.victim or "the runs' victim"
    print(f"\n{victim}: accuracy, ε={args.eps:g}, {args.steps} steps, seeds {args.seeds} "
          "(mean ± standard deviation over seeds)")
    print("| condition | frames | benign | " + " | ".join(runs) + " |")
    print("|---|---|---|" + "---|" * len(runs))
    summary: dict = {}
    for c in conditions:
        mine = [r for r in rows if r["condition"] == c]
        summary[c] = {"benign": statistics.fmean(r["benign"] for r in mine if r["run"] == runs[0])}  # its scene's
        cells = []
        for run in runs:
            values = [r["adversarial"] for r in mine if r["run"] == run]
            summary[c][run] = statistics.fmean(values)
            cells.append(mean_sd(values))
        frames = " / ".join(dict.fromkeys(str(r["frames"]) for r in mine))  # a run's own held-out views differ
        print(f"| {c} | {frames} | {mean_sd([r['benign'] for r in mine if r['run'] == runs[0]])} | "
              + " | ".join(cells) + " |")
    held = [c for c in conditions if not c.startswith("as attacked")]
    print("| mean of the held-out conditions | | " + f"{statistics.fmean(summary[c]['benign'] for c in held):.2f} | "
          + " | ".join(f"{statistics.fmean(summary[c][run] for c in held):.2f}" for run in runs) + " |")
    for run in runs:
        walls = [r["run_wall_s"] for r in rows if r["run"] == run and r["condition"] == conditions[0]]
        print(f"{run}: run wall time {mean_sd(walls)} s")
    _chart(args, conditions, runs, summary)


def _chart(args: argparse.Namespace, conditions: list[str], runs: list[str], summary: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 3.6), dpi=110)
    xs = range(len(conditions))
    width = 0.8 / (1 + len(runs))
    colours = ["#c44", "#36a", "#d90", "#5a5"]
    ax.bar([x - 0.4 + width / 2 for x in xs], [summary[c]["benign"] for c in conditions], width,
           label="benign texture", color="#9bb")
    for i, run in enumerate(runs):
        ax.bar([x - 0.4 + width * (i + 1.5) for x in xs], [summary[c][run] for c in conditions], width,
               label=run, color=colours[i % len(colours)])
    ax.set_xticks(list(xs), [c.replace("_", " ") for c in conditions], rotation=30, ha="right", fontsize=7)
    ax.set_ylim(0, 1)
    ax.set_ylabel("classifier accuracy (0–1)")
    ax.set_title(f"textures on held-out conditions: ε={args.eps:g}, {args.steps} steps, "
                 f"mean of seeds {args.seeds}", fontsize=8)
    ax.legend(fontsize=7)
    runs_arg = " ".join(str(p.resolve().relative_to(ROOT)) if p.resolve().is_relative_to(ROOT) else str(p) for p in args.runs)
    victim = f" --victim {args.victim}" if args.victim else ""
    fig.text(0.01, 0.01, f"made by: scripts/condition_suite.py --out {args.out} --seeds "
             f"{' '.join(map(str, args.seeds))} --eps {args.eps:g} --steps {args.steps} --runs {runs_arg}{victim}",
             fontsize=5)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(args.out / f"conditions_eps{args.eps:g}.png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
