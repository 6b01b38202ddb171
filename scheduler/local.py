"""The whole run in one process: Algorithm 1 through the store, as the farm will run it.

Each iteration plans its frames, runs the per-frame job for each (the farm's
chord header) and then reduce-and-step (the chord's callback). State lives in
the store, so the farm only wraps :func:`scheduler.iteration.frame_job` and
:func:`scheduler.iteration.reduce_and_step` in Celery tasks.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from undream.engine.context import RunContext, build_context
from undream.engine.evaluate import ground_truths, judge, losses, predict, quantise, render_frames
from scheduler.iteration import frame_job, reduce_and_step
from undream.errors import SpecError, already_exists
from undream.color import to_uint8
from undream.progress import progress as progress_bar
from undream.spec.run import RunConfig
from undream.versions import versions

log = logging.getLogger(__name__)


def resolve_scene(config: RunConfig, out: Path, base_dir: Path) -> Path:
    """The run's scene directory: given, or initialised from a spec file into ``out/scene``."""
    from undream.scenedir.init import InitOptions, init_scene

    src = Path(config.scene)
    if not src.is_absolute():
        src = base_dir / src
    if (src / "sequence.json").is_file():
        return src
    if not src.exists():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    return init_scene(src, out / "scene", InitOptions(force=True))


def starting_texture(ctx: RunContext) -> np.ndarray:
    """The scene directory's texture, the attack's T0: sRGB H×W×3 float32 (from the exact float EXR)."""
    from undream.render.loading import read_texture_srgb

    return read_texture_srgb(ctx.scenes.mi, ctx.scene_dir / "textures" / f"{ctx.sequence.texture.name}.exr")


def visibility(ctx: RunContext, texture: np.ndarray) -> np.ndarray:
    """Texels some frame sees (H×W bool): a gradient pass seeded with a white image gradient."""
    from undream.render.differentiable import texture_gradient

    seen = np.zeros(texture.shape[:2], dtype=bool)
    for f in ctx.sequence.frames:
        res = f.camera.resolution
        g = texture_gradient(ctx.scenes, f.index, texture, np.ones((res[1], res[0], 3), np.float32),
                             ctx.config.grad_spp, ctx.config.seed, ctx.config.seed + 1)
        seen |= (g != 0).any(axis=2)
    return seen


def run_local(config: RunConfig, out: str | Path, base_dir: Path | None = None, progress: bool = True,
              force: bool = False) -> dict[str, Any]:
    """Run an attack end to end in this process and write its outputs to ``out``; returns results."""
    import torch

    from undream.attacks import frame_batch, state_to_dict
    from undream.store import open_store

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        if not force:
            raise already_exists(out)
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    scene_dir = resolve_scene(config, out, base_dir or Path.cwd())
    ctx = build_context(config, scene_dir)
    store = open_store(config.store, out / "store")
    T0 = starting_texture(ctx)
    visible = visibility(ctx, T0) if ctx.attack.config.random_start else np.zeros(T0.shape[:2], bool)
    if ctx.attack.config.random_start:
        from PIL import Image
        Image.fromarray(visible.astype(np.uint8) * 255).save(out / "texture_visibility.png")
    T_start, state = ctx.attack.start(torch.from_numpy(T0), visible=torch.from_numpy(visible))
    run_id = store.create_run(config.name, config.to_json(), len(ctx.sequence.frames), config.seed,
                              T_start.numpy(), state_to_dict(state))
    store.set_status(run_id, "running")
    times = {"sim_render": 0.0, "victim": 0.0, "grad_render": 0.0, "reduce_step": 0.0}

    t = time.perf_counter()
    benign_imgs = render_frames(ctx, quantise(T0), out / "frames_benign")
    benign_preds = predict(ctx, benign_imgs)
    times["evaluation"] = time.perf_counter() - t

    steps = ctx.attack.config.steps
    bar = progress_bar(steps, "attack", "it", progress)
    for k in range(steps):
        for pos in frame_batch(len(ctx.sequence.frames), ctx.attack.config.frames_per_step, k, config.seed):
            summary = frame_job(store, ctx, run_id, k, pos)
            for key in ("sim_render", "victim", "grad_render"):
                times[key] += summary["timings"][key]
        t = time.perf_counter()
        reduce_and_step(store, ctx.attack, run_id, k)
        times["reduce_step"] += time.perf_counter() - t
        rec = store.iterations(run_id)[-1]
        bar.update(1)
        bar.set_postfix(loss="n/a" if rec.loss_mean is None else f"{rec.loss_mean:.4f}", bad=rec.n_bad)
    bar.close()

    store.set_status(run_id, "evaluating")
    t = time.perf_counter()
    T_last = store.texture(run_id, steps)
    final_loss = float(np.mean(losses(ctx, render_frames(ctx, T_last, None))))
    from undream.attacks import state_from_dict
    T_final = ctx.attack.final(torch.from_numpy(T_last), final_loss,
                               state_from_dict(store.attack_state(run_id, steps))).numpy()
    T_q = quantise(T_final)
    adv_imgs = render_frames(ctx, T_q, out / "frames_adversarial")
    adv_preds = predict(ctx, adv_imgs)
    times["evaluation"] += time.perf_counter() - t
    times["wall"] = time.perf_counter() - wall0

    results = _results(ctx, store, run_id, benign_preds, adv_preds, times)
    store.set_results(run_id, results)
    store.set_status(run_id, "done")
    _write_outputs(out, ctx, T_q, results, run_id, config)
    return results


def _results(ctx, store, run_id, benign_preds, adv_preds, times) -> dict[str, Any]:
    from undream.metrics import classification_attack_report, detection_attack_report

    benign, adv = judge(ctx, benign_preds), judge(ctx, adv_preds)
    label = ctx.targets[0].label
    if ctx.victim.task == "classification":
        report = classification_attack_report(benign_preds, adv_preds, label, ctx.targets[0].target_label)
    else:
        report = detection_attack_report(benign_preds, adv_preds, ground_truths(ctx), label,
                                         ctx.targets[0].target_label)
    iters = store.iterations(run_id)
    return {
        "run_id": run_id, "victim": ctx.config.victim, "task": ctx.victim.task, "loss_kind": ctx.config.loss,
        "attack": {**ctx.attack.config.to_dict()}, "label": ctx.victim.labels[label],
        "benign": benign, "adversarial": adv, "attack_success": report.to_dict(),
        "loss_per_iteration": [r.loss_mean for r in iters],
        "frames_dropped_per_iteration": [r.n_bad for r in iters],
        "wall_time_seconds": times,
    }


def _write_outputs(out: Path, ctx: RunContext, T_q: np.ndarray, results: dict, run_id: str,
                   config: RunConfig) -> None:
    from PIL import Image

    Image.fromarray(to_uint8(T_q)).save(out / "texture_final.png")
    np.save(out / "texture_final.npy", T_q)
    (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    _loss_plot(results["loss_per_iteration"], out / "loss.png", config)
    meta = {"run_id": run_id, "config": config.to_json(), "seed": config.seed, "scene_dir": str(ctx.scene_dir),
            "texture_final": "8-bit quantised sRGB (texture_final.png); the same values as float in [0, 1] "
                             "(texture_final.npy) — what the adversarial evaluation rendered",
            "versions": {**versions(), "simulator": ctx.sim.name, **ctx.sim.versions()}}
    (out / "metadata.json").write_text(json.dumps(meta, indent=1) + "\n")


def _loss_plot(values: list[float], path: Path, config: RunConfig) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3), dpi=100)
    ax.plot(range(1, len(values) + 1), values, marker=".")
    ax.set_xlabel("iteration")
    ax.set_ylabel(f"mean {config.loss} loss (maximised)")
    ax.set_title(f"{config.name}: {config.attack.get('name')} ε={config.attack.get('eps')}")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
