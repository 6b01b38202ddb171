#!/usr/bin/env python
"""Oracles on the held-out conditions: each condition of examples/conditions/ attacked on its own frames
and judged on them, to learn what a texture can do there at all within a budget.

    .venv/bin/python scripts/condition_oracle.py --out build/oracle16 --victim bundled:classifier-v3 \\
        --eps 16 [--attack apgd] [--steps 200] [--seeds 0] [--conditions fog street] [--conditions-dir DIR]

An oracle attacks the condition it is judged on (every view, none held out): no study number comes from
one. Its accuracy there bounds the study's from below, as far as one optimisation can tell: a texture
attacked on other conditions sees those frames only through transfer, so it leaves the victim right on
about as many of them or more. Every run keeps the main job's render settings (sim_spp 16, grad_spp 8)
and judges itself at 32 spp, as scripts/condition_budget.py judges the held-out conditions. Prints a
table (benign and oracle accuracy per condition, mean ± standard deviation over seeds, and the mean over
conditions), writes ``OUT/oracle_<victim>_<attack>_eps<ε>_steps<N>.csv``. Finished runs in ``OUT/runs``
are read, not redone.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import sys
import time
from pathlib import Path

from condition_suite import mean_sd, run_once, victim_slug

ROOT = Path(__file__).resolve().parents[1]
CONDITIONS = ROOT / "examples" / "conditions"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the runs and the CSV")
    parser.add_argument("--victim", required=True, help="the victim of every run")
    parser.add_argument("--eps", type=float, required=True, help="ε in 0–255 sRGB units")
    parser.add_argument("--attack", default="apgd")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--conditions", nargs="+", help="condition names (default: every spec of the folder)")
    parser.add_argument("--conditions-dir", type=Path, default=CONDITIONS,
                        help="the folder of condition specs (default: examples/conditions)")
    args = parser.parse_args(argv)
    known = sorted(p.stem for p in args.conditions_dir.glob("*.yaml"))
    if not known:
        parser.error(f"--conditions-dir {args.conditions_dir}: holds no condition spec (*.yaml)")
    names = args.conditions or known
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(f"--conditions: {', '.join(unknown)} is not one of {', '.join(known)}")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from undream.cli.options import local_settings

    local_settings()  # Mitsuba's variant and Dr.Jit's pool ($UNDREAM_DRJIT_THREADS), as the commands set them
    from scheduler.local import run_local
    from undream.spec.run import TASK_LOSSES, RunConfig
    from undream.victims import load_victim

    task = load_victim(args.victim).task
    configs = {(name, seed): RunConfig.from_json({  # every config checked before anything runs
        "name": f"oracle_{name}_{args.attack}_eps{args.eps:g}_steps{args.steps}_seed{seed}",
        "scene": str((args.conditions_dir / f"{name}.yaml").resolve()), "victim": args.victim,
        "loss": TASK_LOSSES[task][0],
        "attack": {"name": args.attack, "eps": args.eps, "steps": args.steps, "seed": seed},
        "holdout": "none", "sim_spp": 16, "grad_spp": 8, "eval_spp": 32, "seed": seed})
        for name in names for seed in args.seeds}
    start = time.monotonic()
    rows = []
    victim_name = victim_slug(args.victim)
    for (name, seed), config in configs.items():
        out = args.out / "runs" / victim_name / config.name
        wall = run_once(config, out, run_local)
        results = json.loads((out / "results.json").read_text())
        rows.append({"victim": args.victim, "condition": name, "attack": args.attack, "eps": args.eps,
                     "steps": args.steps, "seed": seed, "frames": len(results["attacked"]["frames"]),
                     "benign": results["attacked"]["benign"]["value"],
                     "oracle": results["attacked"]["adversarial"]["value"], "run_wall_s": wall})
        print(f"{name} seed {seed}: benign {rows[-1]['benign']:.3f}, oracle {rows[-1]['oracle']:.3f} "
              f"({time.monotonic() - start:.0f} s)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / f"oracle_{victim_name}_{args.attack}_eps{args.eps:g}_steps{args.steps}.csv"
    with open(csv_path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    metric = "AP@0.5" if task == "detection" else "accuracy"
    print(f"\n{args.victim}: {metric} of an oracle on each condition ({args.attack}, ε = {args.eps:g}, "
          f"{args.steps} steps; seeds {args.seeds})")
    print("| condition | benign | oracle |\n|---|---|---|")
    per_seed_means = []
    for name in names:
        mine = [r for r in rows if r["condition"] == name]
        print(f"| {name} | {mine[0]['benign']:.2f} | {mean_sd([r['oracle'] for r in mine])} |")
    for seed in args.seeds:
        per_seed_means.append(statistics.fmean(r["oracle"] for r in rows if r["seed"] == seed))
    print(f"| mean of the {len(names)} | {statistics.fmean(r['benign'] for r in rows):.2f} | "
          f"{mean_sd(per_seed_means)} |")
    print(f"run wall time {mean_sd([r['run_wall_s'] for r in rows])} s; {csv_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
