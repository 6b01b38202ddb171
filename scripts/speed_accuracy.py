#!/usr/bin/env python
"""Speed against accuracy: what each modelling knob costs per iteration and what it buys.

    .venv/bin/python scripts/speed_accuracy.py --out build/speed_accuracy [--steps 30] [--eps 16] [--seeds 0 1]

One knob at a time is moved away from the defaults of the main job
(examples/runs/bin_orbit_pgd.yaml on examples/bin_orbit.yaml: 64 px frames,
grad_spp 8, the lean gradient scene with direct light only (prb ``max_depth``
2), every attacked frame in every step, the captured transport):

- ``grad_spp`` 1, 2, 4, 16, 32;
- frame resolution 32, 48, 96 px (the whole pipeline: simulator, victim, gradient);
- integrator depth of the gradient scene 3 and 6 (one and four indirect bounces);
- the full gradient scene (everything the simulator shows: props, sky, ground
  colours) at depth 2 and 6, instead of the lean one;
- ``frames_per_step`` 9 and 4 of the 18 attacked frames (a minibatch per step);
- ``gradient: prb`` (a backward pass per frame and iteration) instead of the transport.

For every setting it measures, in this one process:

- **time per iteration**: the mean of ``--timing-iterations`` iterations
  (simulator frames, victim, texture gradient; one transport capture per 5
  iterations, as in a run) after 5 warm-up ones, each setting timed in a
  process of its own, one after the other (run it on a quiet machine; the
  load average is recorded); the CSV also keeps each run's own figure
  (``run_seconds_per_iteration``, from ``results.json``);
- **gradient fidelity**: the cosine between the iteration's texture gradient
  (sum over the step's frames, at the starting texture, iterations 0–2) and a
  reference: the full scene at depth 6, prb, 1024 spp gradients from 256 spp
  simulator frames, over all attacked frames;
- **held-out success**: the attack run with that setting (PGD, ``--eps``,
  ``--steps``, each seed of ``--seeds``), its final 8-bit texture judged in the
  default 64 px simulator on the held-out views (every 4th, never attacked):
  accuracy and the mean probability of the true class (lower is a stronger attack).

Writes ``OUT/speed_accuracy.csv`` (one row per setting and seed),
``OUT/speed_accuracy.png`` (held-out true-class probability and gradient
cosine against seconds per iteration, Pareto fronts marked) and prints a
table. Scenes and runs are kept under ``OUT`` (``--reuse`` keeps finished runs).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
REF_GRAD_SPP, REF_SIM_SPP = 1024, 256


@dataclass(frozen=True)
class Setting:
    name: str
    knob: str
    value: str
    scene: str = "base"  # key of the scene directory (see _scenes)
    run: dict = field(default_factory=dict)  # run-config overrides


SETTINGS = [
    Setting("default", "default", "grad_spp 8, 64 px, lean depth 2, 18 frames/step, transport"),
    *[Setting(f"grad_spp_{s}", "grad_spp", str(s), run={"grad_spp": s}) for s in (1, 2, 4, 16, 32)],
    *[Setting(f"res_{r}", "resolution (px)", str(r), scene=f"res_{r}") for r in (32, 48, 96)],
    *[Setting(f"lean_depth_{d}", "depth (lean scene)", str(d), scene=f"lean_d{d}") for d in (3, 6)],
    *[Setting(f"full_depth_{d}", "full gradient scene, depth", str(d), scene=f"full_d{d}") for d in (2, 6)],
    *[Setting(f"frames_{k}", "frames per step", str(k), run={"attack.frames_per_step": k}) for k in (9, 4)],
    Setting("prb", "gradient", "prb", run={"gradient": "prb"}),
]
REFERENCE = Setting("reference", "reference", "full depth 6, prb", scene="full_d6",
                    run={"grad_spp": REF_GRAD_SPP, "sim_spp": REF_SIM_SPP, "gradient": "prb"})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scenes, runs and the results")
    parser.add_argument("--eps", type=float, default=16.0, help="ε in 0–255 sRGB units")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--only", nargs="+", help="setting names to run (default: all)")
    parser.add_argument("--timing-iterations", type=int, default=10,
                        help="timed iterations per setting (each setting in a process of its own)")
    parser.add_argument("--time-one", metavar="SETTING", help=argparse.SUPPRESS)  # used by the timing
    parser.add_argument("--reuse", action="store_true", help="keep runs that finished earlier under OUT")
    parser.add_argument("--replot", action="store_true", help="only redraw the table and chart from OUT's CSV")
    args = parser.parse_args(argv)
    if args.replot:
        with open(args.out / "speed_accuracy.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        for r in rows:
            r.update({k: float(r[k]) for k in ("cosine_mean", "cosine_std")})
        _write(args, rows)
        return 0
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT))
    from undream.victims import load_victim

    args.out.mkdir(parents=True, exist_ok=True)
    settings = [s for s in SETTINGS if not args.only or s.name in args.only]
    start = time.monotonic()
    base = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    base.update(attack={**base["attack"], "eps": args.eps, "steps": args.steps})
    scenes = _scenes(args.out / "scenes", {s.scene for s in settings} | {"base", REFERENCE.scene}
                     if not args.time_one else {"base", next(s.scene for s in SETTINGS if s.name == args.time_one)})
    victim = load_victim(base["victim"])
    if args.time_one:
        _time_one(args, base, scenes, next(s for s in SETTINGS if s.name == args.time_one), victim)
        return 0
    print(f"scenes ready ({time.monotonic() - start:.0f} s); load average {_load()}", flush=True)
    ref = _Setup(base, scenes, REFERENCE, victim)
    reference, second = ref.gradient(0), ref.gradient(1)
    ref.close()
    print(f"reference gradient ({time.monotonic() - start:.0f} s): two draws of it agree to cosine "
          f"{_cosine(second, reference):.3f} (its own noise)", flush=True)
    cosines = {}
    for s in settings:
        setup = _Setup(base, scenes, s, victim)
        cosines[s.name] = [_cosine(setup.gradient(it), reference) for it in (0, 1, 2)]
        setup.close()
    print(f"gradient fidelity ({time.monotonic() - start:.0f} s)", flush=True)
    timing = {s.name: _time_in_own_process(args, s) for s in settings}
    timing_load = _load()
    print(f"timing, {args.timing_iterations} iterations a setting ({time.monotonic() - start:.0f} s, "
          f"load {timing_load})", flush=True)
    judge = _Judge(base, scenes["base"], victim)
    rows = []
    for s in settings:
        for seed in args.seeds:
            run = _attack(base, scenes, s, seed, args.out / "runs" / f"{s.name}_s{seed}", args.reuse)
            held = judge(np.load(run / "texture_final.npy"))
            res = json.loads((run / "results.json").read_text())
            t = res["wall_time_seconds"]
            per_iter = (t["sim_render"] + t["victim"] + t["grad_render"] + t["reduce_step"]) / args.steps
            rows.append({"setting": s.name, "knob": s.knob, "value": s.value, "seed": seed,
                         "seconds_per_iteration": round(timing[s.name], 4), "timing_load": timing_load,
                         "run_seconds_per_iteration": round(per_iter, 4),
                         "sim_render_s": round(t["sim_render"] / args.steps, 4),
                         "victim_s": round(t["victim"] / args.steps, 4),
                         "grad_render_s": round(t["grad_render"] / args.steps, 4),
                         "cosine_mean": round(float(np.mean(cosines[s.name])), 4),
                         "cosine_std": round(float(np.std(cosines[s.name])), 4),
                         "held_out_accuracy": held["accuracy"], "held_out_true_prob": held["true_prob"],
                         "attacked_accuracy": res["attacked"]["adversarial"]["value"],
                         "load_average": _load()})
            print(f"{s.name} seed {seed}: {timing[s.name]:.3f} s/iteration (in the run: {per_iter:.3f}), cosine "
                  f"{np.mean(cosines[s.name]):.3f}, held-out "
                  f"accuracy {held['accuracy']:.3f}, p(true) {held['true_prob']:.3f} "
                  f"({time.monotonic() - start:.0f} s, load {_load()})", flush=True)
    _write(args, rows)
    print(f"done in {time.monotonic() - start:.0f} s")
    return 0


# -- scenes ---------------------------------------------------------------------------------------

def _scenes(root: Path, keys: set[str]) -> dict[str, Path]:
    """Scene directories by key: base (64 px), res_R (R px), lean_dD / full_dD (base with its
    gradient scene rebuilt lean or from everything the simulator shows, prb at max_depth D)."""
    from undream.scenedir.init import InitOptions, init_scene

    spec = yaml.safe_load((ROOT / "examples" / "bin_orbit.yaml").read_text())
    out: dict[str, Path] = {}
    for key in sorted(keys, key=lambda k: k != "base"):
        path = root / key
        if (path / "sequence.json").is_file():
            out[key] = path
            continue
        if key == "base" or key.startswith("res_"):
            r = 64 if key == "base" else int(key[4:])
            spec_r = {**spec, "name": f"bin_orbit_{r}px", "camera": {**spec["camera"], "resolution": [r, r]}}
            root.mkdir(parents=True, exist_ok=True)
            spec_path = root / f"{key}.yaml"
            spec_path.write_text(yaml.safe_dump(spec_r))
            out[key] = init_scene(spec_path, path, InitOptions(force=True, progress=False))
        else:
            kind, depth = key.split("_d")
            tmp = root / f".{key}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(out["base"], tmp)
            _rewrite_gradient_scene(tmp, full=kind == "full", depth=int(depth))
            tmp.rename(path)
            out[key] = path
    return out


def _rewrite_gradient_scene(scene_dir: Path, full: bool, depth: int) -> None:
    from undream.scene.layout import frame_xml
    from undream.scene.mitsuba_scene import ScenePaths, scene_dict
    from undream.scene.xml import to_xml
    from undream.spec.io import load_sequence

    seq = load_sequence(scene_dir / "sequence.json")
    for frame in seq.frames:
        d = scene_dict(seq, frame, ScenePaths(".."), "sim" if full else "grad")
        d["integrator"] = {"type": "prb", "max_depth": depth}
        frame_xml(scene_dir, "grad", frame.index).write_text(to_xml(d, {"spp": 16}))


# -- gradients, runs, judging ---------------------------------------------------------------------

def _config(base: dict, scenes: dict[str, Path], s: Setting, seed: int, name: str):
    from scheduler.sweep import set_dotted
    from undream.spec.run import RunConfig

    d = {**base, "seed": seed, "name": name, "scene": str(scenes[s.scene])}
    for key, value in s.run.items():
        set_dotted(d, key, value, f"setting {s.name}")
    return RunConfig.from_json(d)


class _Setup:
    """A setting's run context, computing an iteration's texture gradient (summed over the frames
    that step uses) at the starting texture, as the run with that setting computes it."""

    def __init__(self, base: dict, scenes: dict[str, Path], s: Setting, victim) -> None:
        from undream.engine.algorithm import start_texture as starting_texture
        from undream.engine.context import build_context
        from undream.spec.run import split_frames

        self.config = _config(base, scenes, s, 0, "fidelity")
        self.ctx = build_context(self.config, scenes[s.scene], victim=victim)
        self.attacked, _ = split_frames(self.config.holdout, len(self.ctx.sequence.frames))
        self.texture = starting_texture(self.ctx)

    def gradient(self, iteration: int) -> np.ndarray:
        from undream.attacks.minibatch import frame_batch
        from undream.engine.job import render_and_grad

        k = self.config.attack.frames_per_step
        chosen = [self.attacked[i] for i in frame_batch(len(self.attacked), k, iteration, self.config.seed)]
        return sum(render_and_grad(self.ctx, p, self.texture, iteration).grad for p in chosen)

    def close(self) -> None:
        self.ctx.scenes.close()


def _time_in_own_process(args: argparse.Namespace, s: Setting) -> float:
    """Mean seconds of an iteration of setting ``s``, timed in a process of its own (``--time-one``)."""
    import subprocess

    cmd = [sys.executable, __file__, "--out", str(args.out), "--eps", str(args.eps), "--steps", str(args.steps),
           "--time-one", s.name, "--timing-iterations", str(args.timing_iterations)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return float(json.loads(done.stdout.strip().splitlines()[-1])["seconds_per_iteration"])


def _time_one(args: argparse.Namespace, base: dict, scenes: dict[str, Path], s: Setting, victim) -> None:
    """Print the mean seconds of iterations 5 .. 5 + n - 1 of setting ``s`` (after 0-4 warm the
    scenes, the kernels and the first transports; one capture per 5 iterations, as in a run)."""
    setup = _Setup(base, scenes, s, victim)
    for it in range(5):
        setup.gradient(it)
    t0 = time.perf_counter()
    for it in range(5, 5 + args.timing_iterations):
        setup.gradient(it)
    print(json.dumps({"setting": s.name, "seconds_per_iteration": (time.perf_counter() - t0)
                      / args.timing_iterations}))
    setup.close()


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.ravel(a).astype(np.float64), np.ravel(b).astype(np.float64)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-30))


def _attack(base: dict, scenes: dict[str, Path], s: Setting, seed: int, out: Path, reuse: bool) -> Path:
    from scheduler.local import run_local

    if reuse and (out / "results.json").is_file():
        return out
    config = _config(base, scenes, s, seed, f"{s.name}_s{seed}".replace("_", "-"))
    run_local(config, out, base_dir=ROOT, progress=False, force=True)
    return out


class _Judge:
    """Judges a texture on the held-out views of the default 64 px scene at eval_spp."""

    def __init__(self, base: dict, scene: Path, victim) -> None:
        from undream.engine.context import build_context
        from undream.spec.run import RunConfig, split_frames

        config = RunConfig.from_json({**base, "name": "judge", "scene": str(scene)})
        self.ctx = build_context(config, scene, victim=victim)
        self.held = split_frames(config.holdout, len(self.ctx.sequence.frames))[1]

    def __call__(self, texture: np.ndarray) -> dict[str, float]:
        from undream.engine.algorithm import predict
        from undream.engine.patch import quantise, render_frames

        preds = predict(self.ctx, render_frames(self.ctx, quantise(texture), None))
        labels = [self.ctx.targets[p].label for p in self.held]
        correct = [int(preds[p].label) == y for p, y in zip(self.held, labels)]
        probs = [float(preds[p].probs[y]) for p, y in zip(self.held, labels)]
        return {"accuracy": round(float(np.mean(correct)), 4), "true_prob": round(float(np.mean(probs)), 4)}


def _load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


# -- outputs --------------------------------------------------------------------------------------

def _summary(rows: list[dict]) -> list[dict]:
    out = []
    for name in dict.fromkeys(r["setting"] for r in rows):
        rs = [r for r in rows if r["setting"] == name]
        agg = {k: rs[0][k] for k in ("setting", "knob", "value", "cosine_mean", "cosine_std")}
        for key in ("held_out_accuracy", "held_out_true_prob", "attacked_accuracy"):
            vals = [float(r[key]) for r in rs]
            agg[key], agg[key + "_std"] = float(np.mean(vals)), float(np.std(vals))
        agg["seconds_per_iteration"] = float(rs[0]["seconds_per_iteration"])  # one timing per setting
        out.append(agg)
    return out


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both axes (lower x and lower y are better)."""
    return [i for i, (x, y) in enumerate(points)
            if not any((x2 <= x and y2 <= y) and (x2 < x or y2 < y) for x2, y2 in points)]


def _write(args: argparse.Namespace, rows: list[dict]) -> None:
    with open(args.out / "speed_accuracy.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary = _summary(rows)
    print(f"\nPGD ε={args.eps:g}, {args.steps} steps, seeds {args.seeds}; mean ± std over seeds")
    print("| setting | s/iteration | gradient cosine | held-out accuracy | held-out p(true) | attacked accuracy |")
    print("|---|---|---|---|---|---|")
    for a in summary:
        print(f"| {a['knob']}: {a['value']} | {a['seconds_per_iteration']:.3f} | {a['cosine_mean']:.3f} ± "
              f"{a['cosine_std']:.3f} | {a['held_out_accuracy']:.3f} ± {a['held_out_accuracy_std']:.3f} | "
              f"{a['held_out_true_prob']:.3f} ± {a['held_out_true_prob_std']:.3f} | "
              f"{a['attacked_accuracy']:.3f} ± {a['attacked_accuracy_std']:.3f} |")
    _chart(args, summary)


def _chart(args: argparse.Namespace, summary: list[dict]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), dpi=110)
    xs = [a["seconds_per_iteration"] for a in summary]
    panels = [("held_out_true_prob", "held-out p(true class) after the attack (lower: stronger)", True),
              ("cosine_mean", "gradient cosine to the reference (higher: truer)", False)]
    knobs = list(dict.fromkeys(a["knob"] for a in summary))
    colours = {k: plt.cm.tab10(i) for i, k in enumerate(knobs)}
    for ax, (key, label, lower_better) in zip(axes, panels):
        ys = [a[key] for a in summary]
        front = pareto([(x, y if lower_better else -y) for x, y in zip(xs, ys)])
        for i, a in enumerate(summary):
            err = a.get(key + "_std") if key != "cosine_mean" else a["cosine_std"]
            ax.errorbar(xs[i], ys[i], yerr=err, fmt="o", color=colours[a["knob"]], capsize=2,
                        label=a["knob"], markersize=7 if i in front else 5,
                        markeredgecolor="k" if i in front else colours[a["knob"]])
            ax.annotate(a["value"] if a["knob"] != "default" else "default", (xs[i], ys[i]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
        fx = sorted(front, key=lambda i: xs[i])
        ax.plot([xs[i] for i in fx], [ys[i] for i in fx], "k--", lw=0.8, label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlabel("seconds per iteration (one process, 18 frames of 64 px unless noted)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    seen = dict(zip(labels, handles))
    axes[1].legend(seen.values(), seen.keys(), fontsize=7, loc="lower right")
    fig.suptitle(f"speed against accuracy on bin_orbit: PGD ε={args.eps:g}, {args.steps} steps, "
                 f"seeds {' '.join(map(str, args.seeds))}; one knob at a time away from the defaults", fontsize=9)
    fig.text(0.01, 0.01, f"made by: .venv/bin/python scripts/speed_accuracy.py --out {args.out} --eps {args.eps:g} "
             f"--steps {args.steps} --seeds {' '.join(map(str, args.seeds))}", fontsize=6)
    fig.tight_layout(rect=(0, 0.03, 1, 0.95))
    fig.savefig(args.out / "speed_accuracy.png")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
