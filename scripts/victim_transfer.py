#!/usr/bin/env python
"""Transfer between victims: each farm sweep's final textures judged by every victim on held-out views.

    .venv/bin/python scripts/victim_transfer.py --out build/victim_transfer \\
        [--sweeps bin_orbit_budget bin_orbit_detector_budget bin_orbit_yolo_budget] \\
        [--victims bundled:classifier bundled:detector bundled:yolo] [--scene examples/bin_orbit.yaml]

The sweeps are those of the budget study (docs/results.md), run on a farm whose settings come from
the environment (``UNDREAM_DATABASE_URL``, ``UNDREAM_BLOB_URL``) as for ``undream evaluate``: each
optimised one texture per (attack, ε, seed) against one victim. Every final texture is judged by
every victim with :func:`scheduler.evaluate.evaluate` (what ``undream evaluate SWEEP SCENE --victim
...`` runs) on ``--scene`` at 32 spp, on the views a run holds out (every 4th), beside the scene's
own texture. Prints one table per (attack, ε): rows the victim a texture was optimised against,
columns the judging victim, each cell the held-out adversarial metric (accuracy, or AP@0.5 for
detectors), mean ± standard deviation over the seeds; the first row is the benign value. Writes
``OUT/victim_transfer.csv`` (every texture and judge) and ``OUT/victim_transfer_<attack>_eps<ε>.png``.
"""
from __future__ import annotations

import argparse
import csv
import statistics
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SWEEPS = ["bin_orbit_budget", "bin_orbit_detector_budget", "bin_orbit_yolo_budget"]
VICTIMS = ["bundled:classifier", "bundled:detector", "bundled:yolo"]


def sweep_runs(store, name: str) -> dict:
    """The runs of sweep ``name`` by the name :func:`scheduler.evaluate.farm_textures` gives their textures."""
    from scheduler.evaluate import texture_name

    sweep = store.find_sweep(name)
    return {texture_name(run): run for run in store.runs_page(sweep_id=sweep.id, limit=None, newest_first=False).runs}


def _cell(values: list[float]) -> str:
    if not values:
        return "–"
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):.3f} ± {sd:.3f}"


def chart(path: Path, victims: list[str], sources: list[str], means: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    grid = np.array([[means.get((s, v), np.nan) for v in victims] for s in sources])
    fig, ax = plt.subplots(figsize=(3.2 + 0.9 * len(victims), 1.2 + 0.6 * len(sources)))
    im = ax.imshow(grid, vmin=0, vmax=1, cmap="RdYlGn")
    short = [v.replace("bundled:", "") for v in victims]
    ax.set_xticks(range(len(victims)), short)
    ax.set_yticks(range(len(sources)), ["benign (no attack)" if s == "benign" else f"optimised vs {s.replace('bundled:', '')}"
                                        for s in sources])
    ax.set_xlabel("judged by (held-out views)")
    for i in range(len(sources)):
        for j in range(len(victims)):
            if not np.isnan(grid[i, j]):
                ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=9)
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, fraction=0.05, label="accuracy / AP@0.5")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sweeps", nargs="+", default=SWEEPS)
    parser.add_argument("--victims", nargs="+", default=VICTIMS)
    parser.add_argument("--scene", type=Path, default=ROOT / "examples" / "bin_orbit.yaml")
    parser.add_argument("--spp", type=int, default=32)
    args = parser.parse_args(argv)

    from scheduler.evaluate import evaluate, farm_textures
    from undream.settings import load_local, load_settings
    from undream.store import open_farm_store
    from undream.variant import mitsuba

    local = load_local()
    mitsuba(local.mi_variant)
    settings = load_settings()
    store = open_farm_store(settings, create=False)
    args.out.mkdir(parents=True, exist_ok=True)
    textures, runs, sweep_of = {}, {}, {}
    for name in args.sweeps:
        found = farm_textures(store, name, settings.cache_dir)  # the runs with a final texture
        textures.update(found)
        runs.update(sweep_runs(store, name))
        sweep_of.update(dict.fromkeys(found, name))
    print(f"{len(textures)} textures of {', '.join(args.sweeps)} judged by {', '.join(args.victims)} ...", flush=True)
    rows = []
    for row in evaluate(textures, [args.scene], args.victims, spp=args.spp, local=local):  # benign renders once
        if row["split"] != "held_out":
            continue
        cfg = runs[row["texture"]].run_config
        rows.append({"sweep": sweep_of[row["texture"]], "run": runs[row["texture"]].name, "source": cfg.victim,
                     "attack": cfg.attack.name, "eps": cfg.attack.eps, "seed": cfg.seed, "judge": row["victim"],
                     "metric": row["metric"], "frames": row["frames"], "benign": row["benign"],
                     "adversarial": row["adversarial"]})
    with open(args.out / "victim_transfer.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    cells: dict[tuple, list[float]] = defaultdict(list)
    benign: dict[str, float] = {}
    for r in rows:
        cells[(r["attack"], r["eps"], r["source"], r["judge"])].append(r["adversarial"])
        benign[r["judge"]] = r["benign"]
    sources = list(dict.fromkeys(r["source"] for r in rows))
    for attack, eps in sorted({(r["attack"], r["eps"]) for r in rows}):
        print(f"\n{attack}, ε = {eps:g}: held-out views ({rows[0]['frames']}), adversarial accuracy / AP@0.5, "
              f"mean ± sd over seeds\n")
        print("| optimised against | " + " | ".join(f"judged by {v}" for v in args.victims) + " |")
        print("|---|" + "---|" * len(args.victims))
        print("| (benign) | " + " | ".join(f"{benign.get(v, float('nan')):.3f}" for v in args.victims) + " |")
        means = {("benign", v): benign[v] for v in args.victims if v in benign}
        for s in sources:
            print(f"| {s} | " + " | ".join(_cell(cells[(attack, eps, s, v)]) for v in args.victims) + " |")
            means.update({(s, v): statistics.mean(cells[(attack, eps, s, v)])
                          for v in args.victims if cells[(attack, eps, s, v)]})
        png = args.out / f"victim_transfer_{attack}_eps{eps:g}.png"
        chart(png, args.victims, ["benign", *sources], means,
              f"{attack.upper()} ε = {eps:g}: held-out views, mean over seeds")
        print(f"\nchart: {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
