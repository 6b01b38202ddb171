"""The per-frame job: simulator render → victim loss → Mitsuba backward → texture gradient."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from undream.engine.context import RunContext
from undream.color import linear_to_srgb
from undream.metrics import GroundTruth, is_detected
from undream.render.differentiable import srgb_encode_grad
from undream.render.jitter import draw_conditions


def frame_seed(run_seed: int, iteration: int, frame: int) -> int:
    """A render seed unique to (run, iteration, frame); ``seed + 1`` is its ``seed_grad``."""
    return (run_seed * 1_000_003 + iteration * 10_007 + frame * 2) % (2**31 - 2)


@dataclass
class FrameResult:
    """One frame's texture gradient (H×W×3, d loss / d sRGB texture) and its summary.

    ``prediction``: the victim's verdict on the frame the simulator rendered
    (see :func:`prediction_record`), small plain JSON; ``timings`` in seconds.
    """

    grad: np.ndarray
    loss: float
    finite: bool
    prediction: dict[str, Any] | None
    timings: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """The job's small JSON summary: loss (None if not finite), finiteness, prediction, timings (s)."""
        return {"loss": self.loss if math.isfinite(self.loss) else None, "finite": self.finite,
                "prediction": self.prediction, "timings": self.timings}


def class_score(pred: Any) -> float | None:
    """The probability (0–1, 4 decimals) of a classifier's predicted class, from a live prediction
    (``probs``) or a stored one (``score``); None when a stored one has none."""
    score = pred.probs[int(pred.label)] if hasattr(pred, "probs") else getattr(pred, "score", None)
    return None if score is None else round(float(score), 4)


def ground_truth(target: Any) -> Any:
    """The object's true box and class in one frame (:class:`undream.metrics.GroundTruth`); no box
    where the object is unseen (``target.box`` None)."""
    return GroundTruth.of({"boxes": [target.box] if target.box else np.zeros((0, 4)),
                           "labels": [target.label] if target.box else []})


def prediction_record(ctx: RunContext, position: int, pred: Any) -> dict[str, Any]:
    """The victim's verdict on frame ``position`` as a few JSON values, whatever the model's output size.

    Classifier: ``label`` (predicted class id), ``score`` (its probability,
    0–1, 4 decimals) and ``correct`` (the object's true class). Detector:
    ``detected`` (a detection of the object's class at IoU ≥ 0.5 with its true
    box), ``score`` (the top detection score, 0 without detections) and
    ``n_detections``.
    """
    target = ctx.targets[position]
    if ctx.victim.task == "classification":
        label = int(pred.label)
        return {"label": label, "score": class_score(pred), "correct": label == target.label}
    scores = pred.scores
    return {"detected": bool(is_detected(pred, ground_truth(target), target.label)),
            "n_detections": int(len(scores)),
            "score": round(float(scores.max()), 4) if len(scores) else 0.0}


def victim_loss_and_grad(ctx: RunContext, position: int,
                         image_srgb: np.ndarray) -> tuple[float, np.ndarray, dict[str, Any]]:
    """The victim's loss on one H×W×3 sRGB frame, d loss / d image (H×W×3), and its prediction
    (:func:`prediction_record`)."""
    import torch

    x = torch.from_numpy(np.ascontiguousarray(image_srgb.transpose(2, 0, 1)))[None].requires_grad_(True)
    loss = ctx.victim.loss(x, ctx.targets[position], ctx.config.loss)
    (g,) = torch.autograd.grad(loss, x)
    with torch.no_grad():
        pred = ctx.victim.predict(x.detach())[0]
    record = prediction_record(ctx, position, pred)
    return float(loss.detach()), g[0].permute(1, 2, 0).numpy().astype(np.float32), record


def render_and_grad(ctx: RunContext, position: int, texture: np.ndarray, iteration: int) -> FrameResult:
    """Algorithm 1's inner body for the frame at ``position`` with texture ``texture`` (sRGB H×W×3)."""
    cfg = ctx.config
    index = ctx.frame_indices[position]
    seed = frame_seed(cfg.seed, iteration, index)
    conditions = draw_conditions(cfg.eot, cfg.seed, iteration, index)  # None without eot
    t0 = time.perf_counter()
    linear = ctx.sim.render(index, texture, cfg.sim_spp, seed, conditions=conditions)
    t1 = time.perf_counter()
    loss, g_image, pred = victim_loss_and_grad(ctx, position, linear_to_srgb(linear))
    t2 = time.perf_counter()
    g_linear = srgb_encode_grad(linear, g_image)
    grad = ctx.gradients.texture_gradient(index, texture, g_linear, cfg.grad_spp, iteration, seed, conditions)
    t3 = time.perf_counter()
    # A NaN in the victim's image gradient must not hide behind the renderer: Mitsuba's
    # backward pass turns it into zeros, which would pass as a finite frame.
    finite = bool(np.isfinite(g_image).all() and np.isfinite(grad).all()) and math.isfinite(loss)
    timings = {"sim_render": t1 - t0, "victim": t2 - t1, "grad_render": t3 - t2, "total": t3 - t0}
    return FrameResult(grad, loss, finite, pred, timings)
