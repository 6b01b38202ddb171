#!/usr/bin/env python
"""The main job before and after, measured in one run: a table per component and the ratios.

    .venv/bin/python benchmarks/bench_main_job.py --before c9c2dfa [--seeds 0 1 2] [--config FILE] [--device cuda]

Runs ``undream run`` on the main job (``examples/runs/bin_orbit_pgd.yaml``: 24
frames at 64 px, 18 attacked, 100 PGD iterations) as a user would (a
subprocess, a fresh output folder) with the engine pinned at commit
``--before`` (a git worktree, removed afterwards) and with this checkout,
alternating, once per seed in ``--seeds`` (the config's ``seed`` replaced). Per component the table gives the
seconds that ``results.json`` reports (``wall_time_seconds``: the sum over
frames of the simulator renders, the victim, the texture gradients; the
reduce-and-step callbacks; the evaluation jobs; the run's wall time from
its record to its results) and the process's own wall time, the median over
seeds, and after/before. It also prints the results each run reached
(accuracies on the attacked and held-out frames, the last iteration's mean
loss; their mean ± standard deviation over seeds) and whether the final
textures of each seed are bit-identical. Run it alone: the
machine's load average is printed before and after.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("sim_render", "victim", "grad_render", "reduce_step", "evaluation", "wall")


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--before", default="c9c2dfa", help="commit of the engine before ('' skips it)")
    p.add_argument("--config", default="examples/runs/bin_orbit_pgd.yaml")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--device", help="the victim's torch device (the config's `device`), e.g. cuda")
    p.add_argument("--keep", type=Path, help="keep the run folders under this folder (BEFORE_OR_AFTER SEED)")
    return p.parse_args(argv)


def seeded(config: str, seed: int, device: str | None = None) -> Path:
    """A copy of the run config ``config`` (a path in the repository) with ``seed`` (and the victim's
    ``device`` when given), next to it so its relative scene path still resolves; removed by the caller."""
    import yaml

    src = ROOT / config
    data = {**yaml.safe_load(src.read_text()), "seed": seed, **({"device": device} if device else {})}
    out = src.parent / f".bench-seed{seed}-{os.getpid()}.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))  # a grid's key order orders its conditions
    return out


def run_env(tree: Path) -> dict[str, str]:
    """The environment of ``undream run`` for ``tree``: its code first on ``PYTHONPATH``, and the
    ``PYTHONPATH`` this process was given after it (dependencies installed with ``pip --target``, as
    on a lent GPU machine, are found there)."""
    path = os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, "HF_HUB_OFFLINE": "1"}


def run_once(tree: Path, config: Path, out: Path) -> dict:
    """``undream run`` with the code of ``tree``; its results.json, the process wall time and texture."""
    env = run_env(tree)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(config), "--out", str(out),
                          "--no-progress"], cwd=tree, env=env, capture_output=True, text=True)
    process = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"undream run failed in {tree}:\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}")
    results = json.loads((out / "results.json").read_text())
    return {"results": results, "process": process, "texture": np.load(out / "texture_final.npy")}


def _summary(results: dict) -> str:
    def acc(split: str, side: str) -> str:
        block = results.get(split) or {}
        value = (block.get(side) or {}).get("value")
        return "–" if value is None else f"{value:.3f}"

    losses = results["loss_per_iteration"]
    return (f"attacked {acc('attacked', 'benign')} → {acc('attacked', 'adversarial')}, held out "
            f"{acc('held_out', 'benign')} → {acc('held_out', 'adversarial')}, last mean loss {losses[-1]:.4f}")


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    load = os.getloadavg()
    print(f"{os.cpu_count()} cores, load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    trees: dict[str, Path] = {"after": ROOT}
    with tempfile.TemporaryDirectory(prefix="undream-main-job-") as tmp:
        if args.before:
            trees = {"before": Path(tmp) / "before", **trees}
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(trees["before"]),
                            args.before], check=True)
        try:
            runs: dict[str, list[dict]] = {name: [] for name in trees}
            for seed in args.seeds:
                config = seeded(args.config, seed, args.device)
                try:
                    for name, tree in trees.items():
                        runs[name].append(run_once(tree, config, (args.keep or Path(tmp)) / f"{name}{seed}"))
                        print(f"  {name} seed {seed}: {runs[name][-1]['results']['wall_time_seconds']['wall']:.1f} s",
                              flush=True)
                finally:
                    config.unlink()
        finally:
            if args.before:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(trees["before"])],
                               check=False)
    med = {name: {part: statistics.median(x["results"]["wall_time_seconds"][part] for x in rs) for part in PARTS}
           for name, rs in runs.items()}
    for name, rs in runs.items():
        med[name]["process"] = statistics.median(x["process"] for x in rs)
    names = list(trees)
    print(f"\nmain job ({args.config}), seconds, median over seeds {args.seeds}:\n")
    print("| part | " + " | ".join(names) + (" | after / before |" if "before" in med else " |"))
    print("|---|" + "---|" * len(names) + ("---|" if "before" in med else ""))
    for part in (*PARTS[:-1], "in between", "wall", "process"):
        row = {}
        for name in names:
            m = med[name]
            row[name] = m["wall"] - sum(m[p] for p in PARTS[:-1]) if part == "in between" else m[part]
        ratio = f" {row['after'] / row['before']:.2f} |" if "before" in med and row["before"] else ""
        print(f"| {part} | " + " | ".join(f"{row[n]:.2f}" for n in names) + " |" + ratio)
    if "before" in med:
        print(f"\nrun wall time before / after: {med['before']['wall'] / med['after']['wall']:.2f}× faster; "
              f"evaluation {med['before']['evaluation'] / med['after']['evaluation']:.2f}× faster")
    for name, rs in runs.items():
        for seed, x in zip(args.seeds, rs):
            print(f"{name} seed {seed}: {_summary(x['results'])}")
        last = [x["results"]["loss_per_iteration"][-1] for x in rs]
        held = [(x["results"].get("held_out") or {}).get("adversarial", {}).get("value") for x in rs]
        print(f"{name}: last mean loss {np.mean(last):.4f} ± {np.std(last):.4f}, held-out adversarial accuracy "
              f"{np.mean([h for h in held if h is not None]):.3f} over {len(rs)} seed(s)")
    if "before" in runs:
        same = all(np.array_equal(a["texture"], b["texture"]) for a, b in zip(runs["before"], runs["after"]))
        diff = max(float(np.abs(a["texture"] - b["texture"]).max()) for a, b in zip(runs["before"], runs["after"]))
        print(f"final textures before and after bit-identical (every seed): {same} "
              f"(largest difference {diff * 255:.0f}/255)")
    load = os.getloadavg()
    print(f"load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
