#!/usr/bin/env python
"""Held-out conditions × studies: one chart from the CSVs of scripts/condition_budget.py (and of
scripts/condition_oracle.py, whose ``oracle`` column is read as the score).

    .venv/bin/python scripts/held_out_heatmap.py --out docs/held_out_nights.png \\
        --study "64 nights, 18 frames/step=docs/condition_budget_classifier-v3_pgd_adam255_nights_grid.csv" \\
        --study "64 nights, 36 frames/step=docs/condition_budget_classifier-v3_pgd255_nights_grid_fps36.csv" [...]

Each row is a study (one attack of one CSV: ``--attack``, default the CSV's first), each column a
held-out condition; a cell reads the seeds' scores and is coloured by the study's *worst* seed
(green: ≤ 0.05, issue 22's goal for every seed). The first row is the benign
texture's score (the first CSV's first seed). Prints the same numbers as a Markdown table.
"""
from __future__ import annotations

import argparse
import csv
import statistics
import textwrap
from collections import defaultdict
from pathlib import Path

GOAL = 0.05  # issue 22: the adversarial score on every held-out condition, for every seed
SCORES = ("adversarial", "oracle")  # the score column of a study's CSV: condition_budget's, condition_oracle's

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the chart to write (.png)")
    parser.add_argument("--study", action="append", required=True, metavar="LABEL=CSV",
                        help="a row: its label and a CSV of scripts/condition_budget.py or "
                             "scripts/condition_oracle.py (repeatable)")
    parser.add_argument("--attack", help="the attack of each CSV to show (default: each CSV's first)")
    parser.add_argument("--run", help="the run of each CSV to show (its `run` column: 'one scene', '16 conditions', "
                                          "...), needed where a CSV holds several")
    parser.add_argument("--title", default="the victim on the held-out conditions, per seed")
    args = parser.parse_args(argv)
    studies = []
    for item in args.study:
        label, sep, path = item.rpartition("=")
        if not sep or not label or not Path(path).is_file():
            parser.error(f"--study {item!r}: give LABEL=CSV with an existing CSV file")
        rows = list(csv.DictReader(open(path, newline="")))
        attack = args.attack or (rows[0]["attack"] if rows else None)
        rows = [r for r in rows if r["attack"] == attack]
        if not rows:
            parser.error(f"--study {item!r}: no rows of attack {attack!r}")
        runs = sorted({r["run"] for r in rows if "run" in r})
        if args.run is not None and runs:
            rows = [r for r in rows if r["run"] == args.run]
            if not rows:
                parser.error(f"--study {item!r}: no rows of run {args.run!r} (it holds {', '.join(runs)})")
        elif len(runs) > 1:  # its runs' seeds would be read as one study's
            parser.error(f"--study {item!r}: holds the runs {', '.join(map(repr, runs))}: give --run")
        score = next((column for column in SCORES if column in rows[0]), None)
        if score is None:
            parser.error(f"--study {item!r}: no {' or '.join(SCORES)} column")
        rows = [{**r, "score": r[score]} for r in rows]
        studies.append((label, rows))
    conditions = sorted({r["condition"] for _, rows in studies for r in rows})
    first = studies[0][1]
    benign = {c: next(float(r["benign"]) for r in first if r["condition"] == c and r["seed"] == first[0]["seed"])
              for c in conditions if any(r["condition"] == c for r in first)}
    table = [("benign texture", {c: [v] for c, v in benign.items()})]
    for label, rows in studies:
        per: dict[str, list[float]] = defaultdict(list)
        for r in sorted(rows, key=lambda r: int(r["seed"])):
            per[r["condition"]].append(float(r["score"]))
        table.append((label, per))
    print("| study | " + " | ".join(conditions) + " | mean of the conditions |")
    print("|---|" + "---|" * (len(conditions) + 1))
    for label, per in table:
        cells = [" / ".join(f"{v:.2f}" for v in per[c]) if c in per else "–" for c in conditions]
        means = [statistics.fmean(vals) for vals in zip(*(per[c] for c in conditions if c in per))]
        spread = f"{statistics.fmean(means):.2f}" + (f" ± {statistics.stdev(means):.2f}" if len(means) > 1 else "")
        print(f"| {label} | " + " | ".join(cells) + f" | {spread} |")
    _chart(args, conditions, table)
    return 0


def _chart(args: argparse.Namespace, conditions: list[str], table: list) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.colors import BoundaryNorm, ListedColormap

    worst = np.array([[max(per[c]) if c in per else np.nan for c in conditions] for _, per in table])
    worst[0] = np.nan  # the benign row is read, not coloured
    bounds = [0, GOAL + 1e-9, 0.1, 0.25, 0.5, 1.0]
    cmap = ListedColormap(["#6cc17a", "#d9ef8b", "#fee08b", "#fc8d59", "#d73027"])
    cmap.set_bad("#e8e8e8")
    fig, ax = plt.subplots(figsize=(1.1 * len(conditions) + 3.4, 0.45 * len(table) + 1.9), dpi=110)
    image = ax.imshow(np.ma.masked_invalid(worst), cmap=cmap, norm=BoundaryNorm(bounds, cmap.N), aspect="auto")
    for i, (_, per) in enumerate(table):
        for j, c in enumerate(conditions):
            if c in per:
                ax.text(j, i, " / ".join(f"{v:.2f}" for v in per[c]), ha="center", va="center", fontsize=6)
    ax.set_xticks(range(len(conditions)), [c.replace("_", " ") for c in conditions], fontsize=7, rotation=20)
    ax.set_yticks(range(len(table)), [label for label, _ in table], fontsize=7)
    ax.set_title(f"{args.title} (colour: the worst seed; green: ≤ {GOAL:g} for every seed)", fontsize=8)
    bar = fig.colorbar(image, ax=ax, fraction=0.03, pad=0.02, ticks=bounds)
    bar.ax.tick_params(labelsize=6)
    command = "made by: scripts/held_out_heatmap.py " + (f"--run '{args.run}' " if args.run else "") + \
        " ".join(f"--study '{s}'" for s in args.study)
    lines = textwrap.wrap(command, 190)
    fig.text(0.01, 0.01, "\n".join(lines), fontsize=4.5, va="bottom")
    fig.tight_layout(rect=(0, 0.025 * len(lines), 1, 1))
    fig.savefig(args.out)
    plt.close(fig)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    raise SystemExit(main())
