#!/usr/bin/env python
"""The budget table on held-out conditions: one scene against 16 conditions, PGD and Auto-PGD, each
ε, over seeds; every final texture judged on the eight conditions of examples/conditions/.

    .venv/bin/python scripts/condition_budget.py --out build/condition_budget --victim bundled:yolo \\
        [--seeds 0 1 2] [--eps 8 16 50] [--attacks pgd apgd] [--steps 100] [--multi RUN_CONFIG] [--multi-only] \\
        [--frame-weights unit] [--loss margin] [--step-decay cosine] [--frames-per-step 36] \\
        [--grad-blur 2]

The two run configs are the main job (examples/runs/bin_orbit_pgd.yaml, one scene) and
examples/runs/bin_orbit_conditions.yaml (its scene over 16 conditions, none held out here; ``--multi``:
another multi-condition run config, such as examples/runs/bin_orbit_conditions_wide.yaml), with
``--victim`` and its task's first loss (``ce`` for a classifier, ``vanish`` for a detector), the
attack, ε, steps and seed replaced. The 16-condition scene is initialised once and every
multi-condition run attacks that scene directory (the frames, conditions and per-condition hold-out
of a run of the conditions block). Each run's texture is judged by the victim on every frame of each
held-out condition (accuracy, or AP@0.5 for a detector) at 32 spp (the run configs' ``eval_spp``;
the runs' own evaluation, not used here, at 4 spp: the attack does not depend on it). Prints the table
(mean over the eight conditions; mean ± standard deviation of that over seeds), writes
``OUT/<victim>.csv`` (every run and condition, with each run's wall time) and ``OUT/<victim>.png``
(``OUT/<victim>_<multi config>.csv`` / ``.png`` with ``--multi``).
Finished runs and judgements in ``OUT/runs`` are read, not redone: the script can be stopped and
started again (runs, CSVs and charts of other than 100 steps are named with their steps, so they never
stand in for them;
``--frame-weights unit`` sets every run's ``attack.frame_weights`` and names its runs and files ``_unit``;
``--loss`` another loss than the task's first, the runs and files named ``_<loss>``; ``--step-decay cosine``
PGD's and MI-FGSM's steps shrinking over the run, named ``_cosine``; ``--frames-per-step N`` every run's
minibatch, named ``_fpsN``; ``--grad-blur S`` every run's ``attack.grad_blur`` (the gradient smoothed by a
Gaussian of σ S texels), named ``_blurS``).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import sys
import textwrap
import time
from pathlib import Path

import yaml

from condition_suite import mean_sd, run_once, victim_slug

ROOT = Path(__file__).resolve().parents[1]
ONE_SCENE = ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml"
HELD_OUT = ROOT / "examples" / "conditions"
MULTI = ROOT / "examples" / "runs" / "bin_orbit_conditions.yaml"
JUDGE_SPP = 32  # the run configs' eval_spp: the held-out conditions are judged as the runs judge themselves
RUN_EVAL_SPP = 4  # each run's own evaluation (384 frames twice for 16 conditions) is not used here


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scenes, runs and the results")
    parser.add_argument("--victim", required=True, help="the victim of every run and judgement")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--eps", type=float, nargs="+", default=[8.0, 16.0, 50.0], help="ε in 0–255 sRGB units")
    parser.add_argument("--attacks", nargs="+", default=["pgd", "apgd"])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--multi", type=Path, default=MULTI, help="the multi-condition run config")
    parser.add_argument("--held-out", type=Path, default=HELD_OUT,
                        help="the folder of the held-out conditions' spec files (default examples/conditions)")
    parser.add_argument("--multi-only", action="store_true",
                        help="run the multi-condition config only (the one-scene column is --multi's default's)")
    parser.add_argument("--frame-weights", choices=("mean", "unit"),
                        help="every run's attack.frame_weights (default: each config's own; unit: runs and "
                             "files named _unit)")
    parser.add_argument("--loss", help="every run's loss (default: the victim task's first, ce or vanish; "
                        "another names runs and files _<loss>)")
    parser.add_argument("--step-decay", choices=("none", "cosine"),
                        help="every run's attack.step_decay (pgd, mifgsm; cosine: runs and files named _cosine)")
    parser.add_argument("--frames-per-step", type=int,
                        help="every run's attack.frames_per_step (the minibatch; runs and files named _fps<N>)")
    parser.add_argument("--grad-blur", type=float,
                        help="every run's attack.grad_blur (σ in texels; runs and files named _blur<σ>)")
    args = parser.parse_args(argv)
    if args.grad_blur is not None and not 0 < args.grad_blur <= 64:
        parser.error(f"--grad-blur {args.grad_blur:g}: give a σ in texels, 0 < σ ≤ 64")
    if args.frames_per_step is not None and args.frames_per_step < 1:
        parser.error(f"--frames-per-step {args.frames_per_step}: give a whole number of frames ≥ 1")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from undream.cli.options import local_settings

    local_settings()  # Mitsuba's variant and Dr.Jit's pool ($UNDREAM_DRJIT_THREADS), as the commands set them
    from scheduler.evaluate import evaluate, read_texture, run_scene
    from scheduler.local import run_local
    from undream.scenedir.conditions import conditions_sequence
    from undream.spec.run import TASK_LOSSES, RunConfig
    from undream.victims import load_victim

    start = time.monotonic()
    task = load_victim(args.victim).task
    loss = args.loss or TASK_LOSSES[task][0]
    if loss not in TASK_LOSSES[task]:
        raise SystemExit(f"--loss {loss}: a {task} victim takes {', '.join(TASK_LOSSES[task])}")
    multi = yaml.safe_load(args.multi.read_text())  # read and composed before anything is written
    if not isinstance(multi, dict) or not isinstance(multi.get("conditions"), dict):
        raise SystemExit(f"{args.multi}: --multi needs a run config with a conditions block")
    multi["scene"] = str((args.multi.parent / multi["scene"]).resolve())
    scenes = multi["conditions"].get("scenes") or []  # named from the config's folder, like its scene
    multi["conditions"]["scenes"] = [str((args.multi.parent / s).resolve()) for s in scenes]
    composed = conditions_sequence(RunConfig.from_json({**multi, "victim": args.victim, "loss": loss}), ROOT)
    args.out.mkdir(parents=True, exist_ok=True)
    specs = sorted(args.held_out.glob("*.yaml"))
    if not specs:
        raise SystemExit(f"--held-out {args.held_out}: holds no spec files (*.yaml)")
    held_out = {p.stem: _init_once(p, args.out / "scenes" / p.stem) for p in specs}
    kinds = {"one scene": ONE_SCENE, f"{len(composed.conditions)} conditions": args.multi}
    bases = {"one scene": yaml.safe_load(ONE_SCENE.read_text())}
    bases["one scene"]["scene"] = str((ONE_SCENE.parent / bases["one scene"]["scene"]).resolve())
    default_multi = args.multi.resolve() == MULTI
    scene_name = "_16_conditions" if default_multi else f"_{multi['name']}"
    bases[list(kinds)[1]] = {**{k: v for k, v in multi.items() if k != "conditions"},
                             "scene": str(_init_once(composed, args.out / "scenes" / scene_name))}
    if args.multi_only:
        del kinds["one scene"], bases["one scene"]
    victim_name = victim_slug(args.victim)
    slug = victim_name if default_multi else f"{victim_name}_{multi['name']}"
    method = "" if args.frame_weights in (None, "mean") else f"_{args.frame_weights}"  # names runs and files
    method += "" if args.loss in (None, TASK_LOSSES[task][0]) else f"_{loss}"
    method += "" if args.step_decay in (None, "none") else f"_{args.step_decay}"
    method += "" if args.frames_per_step is None else f"_fps{args.frames_per_step}"
    method += "" if args.grad_blur is None else f"_blur{args.grad_blur:g}"
    suffix = ("" if args.steps == 100 else f"_steps{args.steps}") + method  # 100 steps: the names runs always had
    slug += suffix  # the steps too: a 200-step study wrote over the 100-step one's CSV and chart
    rows = []
    for eps in args.eps:  # each ε's cells whole before the next ε's (a long study stopped early has whole rows)
        for attack in args.attacks:
            for seed in args.seeds:
                for kind, base in bases.items():
                    data = {**base, "name": f"{base['name']}_{attack}_eps{eps:g}{suffix}_seed{seed}", "seed": seed,
                            "victim": args.victim, "loss": loss, "eval_spp": RUN_EVAL_SPP,
                            "attack": {**base["attack"], "name": attack, "eps": eps, "steps": args.steps,
                                       **({"frame_weights": args.frame_weights} if args.frame_weights else {}),
                                       **({"step_decay": args.step_decay} if args.step_decay else {}),
                                       **({"frames_per_step": args.frames_per_step} if args.frames_per_step else {}),
                                       **({"grad_blur": args.grad_blur} if args.grad_blur else {})}}
                    config = RunConfig.from_json(data)
                    out = args.out / "runs" / victim_name / data["name"]
                    wall = run_once(config, out, run_local)
                    judged_file = out / "held_out_conditions.json"
                    if judged_file.is_file():
                        judged = json.loads(judged_file.read_text())
                    else:
                        textures = {data["name"]: (read_texture(out), run_scene(out))}
                        judged = [{"condition": Path(r["scene"]).name, "frames": r["frames"], "benign": r["benign"],
                                   "adversarial": r["adversarial"]}
                                  for r in evaluate(textures, list(held_out.values()), [args.victim],
                                                    spp=JUDGE_SPP) if r["split"] == "all"]
                        judged_file.write_text(json.dumps(judged, indent=1) + "\n")
                    rows += [{"victim": args.victim, "run": kind, "attack": attack, "eps": eps, "seed": seed, **r,
                              "run_wall_s": wall} for r in judged]
                    print(f"{kind} {attack} ε={eps:g} seed {seed}: mean over conditions "
                          f"{statistics.fmean(r['adversarial'] for r in judged):.3f} "
                          f"({time.monotonic() - start:.0f} s)", flush=True)
    _write(args, slug, list(kinds), rows, "AP@0.5" if task == "detection" else "accuracy")
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


def _init_once(source, out: Path) -> Path:
    """``out`` initialised from ``source`` unless an earlier start of the script finished it."""
    from undream.scenedir.init import InitOptions, init_scene

    if (out / "sequence.json").is_file():
        return out
    return init_scene(source, out, InitOptions(force=True))


def _write(args: argparse.Namespace, slug: str, kinds: list[str], rows: list[dict], metric: str) -> None:
    with open(args.out / f"{slug}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    benign = statistics.fmean(r["benign"] for r in rows if r["run"] == kinds[0]
                              and r["seed"] == args.seeds[0] and r["attack"] == args.attacks[0]
                              and r["eps"] == args.eps[0])
    n_held = len({r["condition"] for r in rows})
    print(f"\n{args.victim}: {metric} on the {n_held} held-out conditions (mean over conditions; mean ± standard "
          f"deviation over seeds {args.seeds}), {args.steps} steps; the benign texture: {benign:.2f}")
    print("| attack | ε | " + " | ".join(kinds) + " |")
    print("|---|---|" + "---|" * len(kinds))
    cells: dict = {}
    for attack in args.attacks:
        for eps in args.eps:
            line = []
            for kind in kinds:
                per_seed = [statistics.fmean(r["adversarial"] for r in rows if r["run"] == kind and r["attack"] == attack
                                             and r["eps"] == eps and r["seed"] == seed) for seed in args.seeds]
                cells[attack, eps, kind] = statistics.fmean(per_seed)
                line.append(mean_sd(per_seed))
            print(f"| {attack} | {eps:g} | " + " | ".join(line) + " |")
    for kind in kinds:
        walls = [r["run_wall_s"] for r in rows if r["run"] == kind and r["condition"] == rows[0]["condition"]]
        print(f"{kind}: run wall time {mean_sd(walls)} s")
    _chart(args, slug, kinds, metric, benign, cells)


def _chart(args: argparse.Namespace, slug: str, kinds: list[str], metric: str, benign: float, cells: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.4), dpi=110)
    groups = [(attack, eps) for attack in args.attacks for eps in args.eps]
    width = 0.8 / len(kinds)
    for i, (kind, colour) in enumerate(zip(kinds, ["#c44", "#36a"])):
        ax.bar([x - 0.4 + width * (i + 0.5) for x in range(len(groups))],
               [cells[attack, eps, kind] for attack, eps in groups], width, label=kind, color=colour)
    ax.axhline(benign, color="#888", linestyle="--", linewidth=1, label="benign texture")
    ax.set_xticks(range(len(groups)), [f"{attack} ε={eps:g}" for attack, eps in groups], fontsize=7)
    ax.set_ylim(0, 1)
    ax.set_ylabel(f"{metric}, mean of the held-out conditions", fontsize=8)
    ax.set_title(f"{args.victim}: textures on held-out conditions, {args.steps} steps, seeds {args.seeds}",
                 fontsize=8)
    ax.legend(fontsize=7)
    command = (f"made by: scripts/condition_budget.py --out {args.out} --victim {args.victim} --seeds "
               f"{' '.join(map(str, args.seeds))} --eps {' '.join(f'{e:g}' for e in args.eps)} --attacks "
               f"{' '.join(args.attacks)} --steps {args.steps}"
               + ("" if args.multi.resolve() == MULTI else f" --multi {_shown(args.multi)}")
               + ("" if args.held_out.resolve() == HELD_OUT else f" --held-out {_shown(args.held_out)}")
               + (f" --frame-weights {args.frame_weights}" if args.frame_weights else "")
               + (f" --loss {args.loss}" if args.loss else "")
               + (f" --step-decay {args.step_decay}" if args.step_decay else "")
               + (f" --frames-per-step {args.frames_per_step}" if args.frames_per_step else "")
               + (f" --grad-blur {args.grad_blur:g}" if args.grad_blur else ""))
    lines = textwrap.wrap(command, 140)  # the whole command, however long its paths: one line was cut off
    fig.text(0.01, 0.01, "\n".join(lines), fontsize=5, va="bottom")
    fig.tight_layout(rect=(0, 0.02 + 0.02 * len(lines), 1, 1))
    fig.savefig(args.out / f"{slug}.png")
    plt.close(fig)


def _shown(path: Path) -> str:
    """``path`` relative to the repository where it is inside it."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


if __name__ == "__main__":
    sys.exit(main())
