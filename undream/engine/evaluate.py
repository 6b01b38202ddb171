"""Benign and adversarial evaluation: re-render every frame in the simulator and judge it."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from undream.engine.context import RunContext
from undream.engine.job import class_score, frame_seed, ground_truth
from undream.color import to_uint8
from undream.color import linear_to_srgb
from undream.metrics import accuracy, average_precision, correct, is_detected
from undream.scene.layout import frame_name

EVAL_ITERATION = 10**6  # seeds of evaluation renders never coincide with the attack's


def quantise(texture: np.ndarray) -> np.ndarray:
    """The 8-bit texture a user would print or import into a simulator, back in [0, 1]."""
    return to_uint8(texture).astype(np.float32) / 255.0


def render_frames(ctx: RunContext, texture: np.ndarray, out_dir: Path | None) -> list[np.ndarray]:
    """Every frame at ``eval_spp`` with ``texture`` (sRGB H×W×3); saved as PNGs when ``out_dir`` is set."""
    images = []
    for f in ctx.sequence.frames:
        img = linear_to_srgb(ctx.sim.render(f.index, texture, ctx.config.eval_spp,
                                            frame_seed(ctx.config.seed, EVAL_ITERATION, f.index)))
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(to_uint8(img)).save(out_dir / f"{frame_name('frame', f.index)}.png")
        images.append(img)
    return images


def _batch(images: list[np.ndarray]):
    import torch
    return torch.from_numpy(np.stack([im.transpose(2, 0, 1) for im in images]).astype(np.float32))


def predict(ctx: RunContext, images: list[np.ndarray]) -> list[Any]:
    import torch
    with torch.no_grad():
        return [ctx.victim.predict(_batch([im]))[0] for im in images]


def ground_truths(ctx: RunContext) -> list[Any]:
    """The object's box per frame (from its visibility mask); no box where it is unseen."""
    return [ground_truth(t) for t in ctx.targets]


def judge(ctx: RunContext, preds: list[Any], positions: list[int] | None = None) -> dict[str, Any]:
    """Per-frame correctness and the overall measure (accuracy, or AP@0.5 of the object's class)
    over the frames at ``positions`` (default all; ``preds`` holds one prediction per frame)."""
    keep = list(range(len(preds))) if positions is None else list(positions)
    frames, preds = [ctx.sequence.frames[i] for i in keep], [preds[i] for i in keep]
    label = ctx.targets[0].label
    if ctx.victim.task == "classification":
        ok = correct(preds, label)
        rows = [{"frame": f.index, "prediction": int(p.label), "class": ctx.victim.labels[int(p.label)],
                 "score": class_score(p), "correct": bool(c)}
                for f, p, c in zip(frames, preds, ok)]
        return {"metric": "accuracy", "value": accuracy(preds, label) if preds else None, "per_frame": rows}
    truths = [ground_truth(ctx.targets[i]) for i in keep]
    rows = [{"frame": f.index, "detected": bool(is_detected(p, gt, label)), "n_detections": int(len(p.scores)),
             "score": round(float(p.scores.max()), 4) if len(p.scores) else 0.0}
            for f, p, gt in zip(frames, preds, truths)]
    value = average_precision(preds, truths, label) if preds else None
    return {"metric": "ap50", "value": value, "per_frame": rows}
