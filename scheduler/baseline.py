"""``undream baseline``: the pasted-patch pipeline on a run config, judged in the simulator.

Writes ``OUT/baseline.json`` (what the image-space pipeline reports on its
own pasted images, and what the simulator shows when the patch is worn as the
texture, on the attacked and the held-out frames; the loss per step; the
number of victim evaluations), ``OUT/patch.png`` / ``patch.npy`` (the 8-bit
patch that was evaluated) and ``OUT/scene`` when the run names a spec file.
See :mod:`undream.engine.patch` for the pipeline.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from undream.errors import SpecError, already_exists
from undream.spec.io import check_writable_target
from undream.spec.run import RunConfig, split_frames

MARK = "baseline.json"


def run_patch_baseline(config: RunConfig, out: Path, base_dir: Path, force: bool = False,
                       progress: bool = True, source: Path | None = None) -> dict[str, Any]:
    """Optimise the pasted patch on the run's attacked frames, judge it in the simulator; the results."""
    from PIL import Image

    from scheduler.local import resolve_scene
    from scheduler.preflight import preflight, scene_source
    from scheduler.texture0 import starting_texture
    from undream.color import to_uint8
    from undream.engine.context import build_context
    from undream.engine.evaluate import quantise
    from undream.engine.patch import evaluate_texture, optimise_patch
    from undream.progress import progress as progress_bar

    out = Path(out).resolve()
    check_writable_target(out)
    scene = scene_source(config, base_dir)
    if out == scene or out in scene.parents:
        raise SpecError(f"--out {out}: holds the run's scene {scene}; choose another output folder")
    if out.exists() and any(out.iterdir()):
        if not force:
            raise already_exists(out)
        if not (out / MARK).is_file():
            raise SpecError(f"--out {out}: --force only replaces a folder `undream baseline` wrote "
                            f"(one with its {MARK}); this one has none, so it is left as it is")
    victim = preflight(config, base_dir, source).victim
    if config.attack.get("name") != "pgd":
        raise SpecError(f"{source or 'run'}: attack.name: the pasted-patch baseline runs PGD, "
                        f"got {config.attack.get('name')!r}")
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    ctx = build_context(config, resolve_scene(config, out, base_dir), victim=victim)
    attacked, held = split_frames(config.holdout, len(ctx.sequence.frames))
    T0 = starting_texture(ctx)
    bar = progress_bar(ctx.attack.config.steps, "patch", "step", progress)
    try:
        patch, losses = optimise_patch(ctx, attacked, T0, bar)
    finally:
        bar.close()
    patch_q = quantise(patch)
    splits = {"attacked": attacked, "held_out": held}
    results = {
        "pipeline": "patch optimised in image space on the attacked frames (pasted into the object's mask "
                    "box), then worn as the object's texture and rendered by the simulator",
        "victim": config.victim, "loss_kind": config.loss, "attack": ctx.attack.config.to_dict(),
        "victim_evaluations": ctx.attack.config.steps * len(attacked),
        "in_image_space": _image_space(ctx, attacked, T0, patch_q),
        "benign": evaluate_texture(ctx, T0, splits),
        "in_simulator": evaluate_texture(ctx, patch_q, splits),
        "loss_per_step": losses,
    }
    Image.fromarray(to_uint8(patch_q)).save(out / "patch.png")
    np.save(out / "patch.npy", patch_q)
    (out / MARK).write_text(json.dumps(results, indent=1) + "\n")
    return results


def _image_space(ctx: Any, positions: list[int], texture0: np.ndarray, patch: np.ndarray) -> dict[str, Any]:
    """What the image-space pipeline itself reports: the victim on its pasted images (8-bit patch)."""
    import torch

    from undream.color import linear_to_srgb
    from undream.engine.evaluate import judge
    from undream.engine.job import frame_seed
    from undream.engine.patch import footprints, paste

    cfg, feet = ctx.config, footprints(ctx, positions)
    P = torch.from_numpy(np.ascontiguousarray(patch.transpose(2, 0, 1)))
    preds = [None] * len(ctx.sequence.frames)
    with torch.no_grad():
        for f in feet:
            index = ctx.frame_indices[f.position]
            image = linear_to_srgb(ctx.sim.render(index, texture0, cfg.sim_spp, frame_seed(cfg.seed, 0, index)))
            pasted = paste(torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))), P, f)
            preds[f.position] = ctx.victim.predict(pasted[None])[0]
    judged = judge(ctx, preds, [f.position for f in feet])
    return {"frames": [ctx.frame_indices[f.position] for f in feet], "metric": judged["metric"],
            "value": judged["value"]}
