"""``undream baseline``: the pasted-patch pipeline on a run config, judged in the simulator.

Writes ``OUT/baseline.json`` (what the image-space pipeline reports on its
own pasted images, and what the simulator shows when the patch is worn as the
texture, on the attacked and the held-out frames; the loss per step; the
number of victim evaluations), ``OUT/patch.png`` / ``patch.npy`` (the 8-bit
patch that was evaluated) and ``OUT/scene`` when the run names a spec file. The folder is claimed
atomically after the checks (:func:`scheduler.preflight.claim_output`); a baseline that fails or is
signalled removes it.
See :mod:`undream.engine.patch` for the pipeline.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from scheduler.preflight import check_output_folder, claim_output, preflight, scene_source, scene_sources
from undream.color import to_uint8
from undream.errors import SpecError
from undream.progress import progress as progress_bar
from undream.settings import LocalSettings
from undream.spec.io import atomic_write
from undream.spec.run import RunConfig

MARK = "baseline.json"


def run_patch_baseline(config: RunConfig, out: Path, base_dir: Path, force: bool = False,
                       progress: bool = True, source: Path | None = None,
                       local: LocalSettings = LocalSettings()) -> dict[str, Any]:
    """Optimise the pasted patch on the run's attacked frames, judge it in the simulator; the results.

    ``local``: this process's settings, read at the edge (:func:`undream.settings.load_local`)."""
    from undream.attacks import make_attack
    from undream.engine.patch import check_attack

    out = Path(out).resolve()
    check_output_folder(out, scene_source(config, base_dir), force, command="undream baseline", marker=MARK,
                        inputs=(source, *scene_sources(config, base_dir)[1:]))
    replace = out.exists() and any(out.iterdir())  # as checked: --force and an earlier baseline's folder
    victim = preflight(config, base_dir, source, local).victim
    try:
        check_attack(make_attack(config.attack))
    except SpecError as err:
        raise SpecError(f"{source or 'run'}: {err}") from None
    if replace:
        shutil.rmtree(out)
    # Atomic: of two baselines (or a baseline and a run) on one new --out, the later refuses and
    # deletes nothing; before, it removed the folder the first had begun to write.
    claim_output(out, config, marker=MARK, command="baseline")
    try:  # a failure or a signal removes the folder this baseline claimed (nothing to resume)
        results, patch_q = _baseline(config, out, base_dir, progress, victim, local)
        atomic_write(out / "patch.png", lambda f: Image.fromarray(to_uint8(patch_q)).save(f, format="PNG"))
        atomic_write(out / "patch.npy", lambda f: np.save(f, patch_q))
        atomic_write(out / MARK, json.dumps(results, indent=1) + "\n")  # last: replaces the claim
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return results


def _baseline(config: RunConfig, out: Path, base_dir: Path, progress: bool, victim: Any,
              local: LocalSettings) -> tuple[dict[str, Any], np.ndarray]:
    """The baseline's results and its 8-bit patch (H×W×3 sRGB in [0, 1]); the scene, when the run
    names a spec file, initialised under ``out``."""
    from scheduler.local import resolve_scene
    from undream.engine.context import build_context
    from undream.engine.algorithm import quantise, start_texture
    from undream.engine.patch import benign_frames, evaluate_texture, judge_pasted, optimise_patch

    ctx = build_context(config, resolve_scene(config, out, base_dir, local=local), victim=victim, local=local)
    attacked, held = config.split(ctx.sequence)
    T0 = start_texture(ctx)
    frames = benign_frames(ctx, attacked, T0)
    bar = progress_bar(ctx.attack.config.steps, "patch", "step", progress)
    try:
        patch, losses = optimise_patch(ctx, frames, T0, bar)
    finally:
        bar.close()
    patch_q = quantise(patch)
    splits = {"attacked": attacked, "held_out": held}
    results = {
        "pipeline": "patch optimised in image space on the attacked frames (pasted into the object's mask "
                    "box), then worn as the object's texture and rendered by the simulator",
        "victim": config.victim, "loss_kind": config.loss, "attack": ctx.attack.config.to_dict(),
        "victim_evaluations": ctx.attack.config.steps * len(attacked),
        "in_image_space": judge_pasted(ctx, frames, patch_q),
        "benign": evaluate_texture(ctx, T0, splits),
        "in_simulator": evaluate_texture(ctx, patch_q, splits),
        "loss_per_step": losses,
    }
    return results, patch_q
