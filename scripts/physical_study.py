#!/usr/bin/env python
"""How smooth and printable attacked textures are, against how well they attack (issue 44's tables
and Pareto chart).

    .venv/bin/python scripts/physical_study.py build/stop_sign_physical/* [--out build/physical_study]

For each ``undream run`` output folder (a farm sweep's ``--out`` holds one per run): the run's
attack, ε, seed and physical settings (``regularise``, ``gamut``, ``eot_print``, from its
``metadata.json``), and of its final texture (``texture_final.npy``, sRGB 0–1):

- ``tv``: total variation as Thys et al. 2019 (mean |T[i,j+1] − T[i,j]| + mean |T[i+1,j] − T[i,j]|,
  exact absolute values);
- ``nps``: the mean distance (sRGB 0–1) of a texel to the nearest colour of the shipped printable
  palette (undream/data/palettes/printable.csv);
- ``in_gamut``: the fraction of texels the printer's gamut projection (``gamut: default``,
  docs/printing.md) leaves as they are; empty where setup fetched no profile;
- the detection rate (frames where the object is found, score ≥ the victim's threshold, IoU ≥ 0.5)
  and AP@0.5 on the held-out conditions, held-out views and attacked views, benign and adversarial
  (from ``results.json``).

Writes ``runs.csv`` (a row per run), ``groups.csv`` (mean ± sd over the seeds of each setting) and
``pareto.png`` (held-out-condition detection rate against TV and against NPS, a point per setting
with the seeds' spread) to ``--out``, and prints the groups as a Markdown table.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SPLITS = ("held_out_conditions", "held_out", "attacked")


def texture_measures(texture: np.ndarray, palette: np.ndarray, gamut: Any) -> dict[str, float | None]:
    """TV (Thys, exact) and NPS against ``palette`` (N×3 sRGB 0–1): the regularisers a run weighs
    (:mod:`undream.attacks.regularise`) with exact absolute values (no smoothing), and the fraction
    of texels in ``gamut``."""
    import torch

    from undream.attacks.regularise import palette_distance, total_variation

    T = torch.from_numpy(np.asarray(texture, np.float64))
    tv = float(total_variation(T, delta=0.0))
    nps = float(palette_distance(T, torch.from_numpy(palette), delta=0.0))
    in_gamut = None if gamut is None else float(gamut.contains(np.asarray(texture, np.float32)).mean())
    return {"tv": tv, "nps": nps, "in_gamut": in_gamut}


def split_rates(results: dict[str, Any]) -> dict[str, float | None]:
    """Detection rate and AP@0.5, benign and adversarial, on each split of a detector run."""
    out: dict[str, float | None] = {}
    for phase in ("benign", "adversarial"):
        detected = {row["frame"]: bool(row["detected"]) for row in results[phase]["per_frame"]}
        for split in SPLITS:
            part = results.get(split)
            if not part:
                out[f"{split}_{phase}_rate"] = out[f"{split}_{phase}_ap"] = None
                continue
            frames = part["frames"]
            out[f"{split}_{phase}_rate"] = sum(detected[f] for f in frames) / len(frames)
            out[f"{split}_{phase}_ap"] = part[phase]["value"]
    return out


def setting(config: dict[str, Any]) -> dict[str, Any]:
    """What a run's physical settings and attack were (the seed apart)."""
    reg = config.get("regularise") or {}
    eot = config.get("eot_print") or {}
    return {"attack": config["attack"]["name"], "eps": config["attack"]["eps"],
            "step_decay": config["attack"].get("step_decay") or "none",
            "step_size": config["attack"].get("step_size") or 0.0,
            "grad_blur": config["attack"].get("grad_blur") or 0.0,
            "tv_weight": reg.get("tv", 0.0) or 0.0, "nps_weight": reg.get("nps", 0.0) or 0.0,
            "gamut": config.get("gamut") or "none",
            "eot_print": ",".join(f"{k}={v}" for k, v in sorted(eot.items()) if v) or "none"}


def read_run(folder: Path, palette: np.ndarray, gamut: Any) -> dict[str, Any]:
    meta = json.loads((folder / "metadata.json").read_text())
    config = meta.get("config") or meta.get("run_config")
    if config is None:
        raise SystemExit(f"{folder}/metadata.json: no run config in it")
    results = json.loads((folder / "results.json").read_text())
    row = {"run": folder.name, **setting(config), "seed": config.get("seed", 0)}
    row.update(texture_measures(np.load(folder / "texture_final.npy"), palette, gamut))
    row.update(split_rates(results))
    return row


def groups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and sd over the seeds of each setting, of every numeric column."""
    keys = ("attack", "eps", "step_decay", "step_size", "grad_blur", "tv_weight", "nps_weight", "gamut", "eot_print")
    by: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by[tuple(r[k] for k in keys)].append(r)
    out = []
    for key, members in sorted(by.items(), key=lambda kv: tuple(str(v) for v in kv[0])):
        g: dict[str, Any] = dict(zip(keys, key))
        g["seeds"] = " ".join(str(m["seed"]) for m in sorted(members, key=lambda m: m["seed"]))
        for col in members[0]:
            vals = [m[col] for m in members if isinstance(m[col], (int, float)) and not isinstance(m[col], bool)]
            if col in keys or col == "seed" or not vals or len(vals) != len(members):
                continue
            g[col] = statistics.fmean(vals)
            g[f"{col}_sd"] = statistics.stdev(vals) if len(vals) > 1 else 0.0
        out.append(g)
    return out


def label(g: dict[str, Any]) -> str:
    parts = [f"{'Auto-PGD' if g['attack'] == 'apgd' else g['attack'].upper()} ε{g['eps']:g}"
             + (f" ({g['step_decay']} step)" if g["step_decay"] != "none" else "")
             + (f", {'η₀' if g['attack'] == 'apgd' else 'step'} {g['step_size']:g}" if g["step_size"] else "")
             + (f", gradient blur σ {g['grad_blur']:g}" if g["grad_blur"] else "")]
    if g["tv_weight"]:
        parts.append(f"tv {g['tv_weight']:g}")
    if g["nps_weight"]:
        parts.append(f"nps {g['nps_weight']:g}")
    if g["gamut"] != "none":
        parts.append("gamut")
    if g["eot_print"] != "none":
        parts.append("print EOT")
    return ", ".join(parts)


def chart(gs: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), sharey=True)
    y, ysd = "held_out_conditions_adversarial_rate", "held_out_conditions_adversarial_rate_sd"
    for ax, x in zip(axes, ("tv", "nps")):
        for i, g in enumerate(gs):
            if g.get(y) is None:
                continue
            marker = "o" if g["attack"] == "pgd" else "s"
            filled = g["gamut"] != "none"
            colour = plt.cm.tab20(i % 20)  # tab10's 10 colours would repeat past 10 settings
            ax.errorbar(g[x], g[y], xerr=g.get(f"{x}_sd", 0), yerr=g.get(ysd, 0), fmt=marker, color=colour,
                        mfc=colour if filled else "white", capsize=3, label=label(g))
        ax.set_xlabel({"tv": "total variation of the texture (Thys et al.)",
                       "nps": "non-printability (mean distance to the printable palette, sRGB)"}[x])
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("detection rate, held-out conditions")
    axes[0].set_ylim(-0.03, 1.03)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="center right", fontsize=7, frameon=False)
    fig.suptitle("Attack strength against smoothness and printability (mean ± sd over seeds; "
                 "filled: gamut projection)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 0.78, 1))
    fig.savefig(path, dpi=130)


def markdown(gs: list[dict[str, Any]]) -> str:
    def ms(g: dict[str, Any], col: str, digits: int = 3) -> str:
        if g.get(col) is None:
            return "–"
        return f"{g[col]:.{digits}f} ± {g.get(col + '_sd', 0):.{digits}f}"

    lines = ["| setting | seeds | TV | NPS | in gamut | held-out conditions: rate (benign → adv) | AP adv | "
             "held-out views: rate adv | attacked views: rate adv |", "|---|---|---|---|---|---|---|---|---|"]
    for g in gs:
        lines.append(f"| {label(g)} | {g['seeds']} | {ms(g, 'tv')} | {ms(g, 'nps')} | {ms(g, 'in_gamut', 2)} | "
                     f"{g.get('held_out_conditions_benign_rate', 0):.2f} → {ms(g, 'held_out_conditions_adversarial_rate', 2)} | "
                     f"{ms(g, 'held_out_conditions_adversarial_ap')} | {ms(g, 'held_out_adversarial_rate', 2)} | "
                     f"{ms(g, 'attacked_adversarial_rate', 2)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="undream run output folders")
    p.add_argument("--out", type=Path, default=ROOT / "build" / "physical_study")
    args = p.parse_args(argv)

    from undream.printing.profiles import default_profile
    from undream.settings import load_local
    from undream.spec.physical import read_palette

    palette = np.asarray(read_palette("palette", "printable"), np.float64) / 255.0  # the CSV is 0-255
    profile = default_profile(load_local().undream_cache)
    gamut = None
    if profile.is_file():
        from undream.printing.gamut import load_gamut

        gamut = load_gamut(profile)
    rows = [read_run(f, palette, gamut) for f in args.runs if (f / "results.json").is_file()]
    if not rows:
        raise SystemExit("no finished run among the folders given (none has results.json)")
    gs = groups(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, table in (("runs.csv", rows), ("groups.csv", gs)):
        cols = list(dict.fromkeys(k for r in table for k in r))
        with open(args.out / name, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols)
            w.writeheader()
            w.writerows(table)
    chart(gs, args.out / "pareto.png")
    print(markdown(gs))
    print(f"\nwrote {args.out / 'runs.csv'}, {args.out / 'groups.csv'}, {args.out / 'pareto.png'}")


if __name__ == "__main__":
    main()
