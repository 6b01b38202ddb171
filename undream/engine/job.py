"""The per-frame job: simulator render → victim loss → Mitsuba backward → texture gradient."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from undream.attacks.print_capture import capture_noise, draw_print, printed, texture_vjp
from undream.engine.context import RunContext
from undream.engine.seeds import frame_seed
from undream.color import linear_to_srgb
from undream.metrics import GroundTruth, is_detected
from undream.render.differentiable import srgb_encode_grad
from undream.render.jitter import draw_conditions
from undream.victims.defended import attacker_view


MAX_BOXES = 5  # detections per frame kept in results.json (the highest-scoring)


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


def top_detections(pred: Any, labels: Sequence[str], n: int = MAX_BOXES) -> list[dict[str, Any]]:
    """A detector's kept detections (after its score threshold and NMS, as ``pred`` holds them) as
    small JSON: the ``n`` highest-scoring, each ``{"box": [x0, y0, x1, y1], "score", "label"}`` with the
    box in frame pixels (0.1 px), the score 0–1 (4 decimals) and the label the class name."""
    scores = np.asarray(pred.scores, np.float64).reshape(-1)
    boxes = np.asarray(pred.boxes, np.float64).reshape(-1, 4)
    ids = np.asarray(pred.labels, np.int64).reshape(-1)
    order = np.argsort(-scores, kind="stable")[:n]
    return [{"box": [round(float(v), 1) for v in boxes[i]], "score": round(float(scores[i]), 4),
             "label": labels[int(ids[i])] if 0 <= ids[i] < len(labels) else str(int(ids[i]))}
            for i in order]


def truth_box(target: Any) -> list[float] | None:
    """The object's true box in one frame (its mask box, x1/y1 exclusive, frame pixels, 0.1 px);
    None where the object is unseen."""
    return [round(float(v), 1) for v in target.box] if target.box else None


def detection_boxes(ctx: RunContext, position: int, pred: Any) -> dict[str, Any]:
    """What a page needs to draw a detector's verdict on frame ``position``, as small JSON:
    ``detected`` (as :func:`prediction_record`), ``detections`` (:func:`top_detections`),
    ``truth_box`` (:func:`truth_box`) and ``truth_label`` (the object's class name)."""
    target = ctx.targets[position]
    return {"detected": bool(is_detected(pred, ground_truth(target), target.label)),
            "detections": top_detections(pred, ctx.victim.labels), "truth_box": truth_box(target),
            "truth_label": ctx.victim.labels[target.label]}


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
    (:func:`prediction_record`): :func:`victim_pass` on a batch of one."""
    (loss,), (grad,), (record,) = victim_pass(ctx, [position], [image_srgb])
    return loss, grad, record


def victim_pass(ctx: RunContext, positions: Sequence[int], images_srgb: Sequence[np.ndarray],
                iteration: int | None = None) -> tuple[list[float], list[np.ndarray], list[dict[str, Any]]]:
    """The victim ONCE on the frames at ``positions`` (H×W×3 sRGB images of one size, stacked into
    a batch), forward and backward: each frame's loss, d loss / d image (H×W×3) and prediction record.

    The backward pass is that of the SUM of the per-frame losses, so each frame's image gradient is
    its own loss's (images do not interact in an eval-mode model), equal to a pass on the frame
    alone up to float rounding; the predictions come from the same forward pass.

    The victim is the attack's view of the run's (:func:`undream.victims.defended.attacker_view`):
    behind an adaptive defence, its random transforms drawn from (seed, ``iteration``, frame index).
    """
    import torch

    x = stack_images(images_srgb).requires_grad_(True)
    victim = attacker_view(ctx.victim, ctx.config.seed, iteration, [ctx.frame_indices[p] for p in positions])
    losses, preds = victim.loss_and_predict(x, [ctx.targets[p] for p in positions], ctx.config.loss)
    (g,) = torch.autograd.grad(losses.sum(), x)
    grads = np.ascontiguousarray(g.permute(0, 2, 3, 1).numpy(), dtype=np.float32)
    values = losses.detach().double().tolist()
    return values, list(grads), [prediction_record(ctx, p, pred) for p, pred in zip(positions, preds)]


def stack_images(images_srgb: Sequence[np.ndarray]) -> Any:
    """H×W×3 sRGB images of one size as the victim's input: a float32 B×3×H×W torch tensor."""
    import torch

    return torch.from_numpy(np.stack([np.asarray(im, np.float32).transpose(2, 0, 1) for im in images_srgb]))


def victim_batches(shapes: Sequence[tuple[int, ...]], size: int) -> list[list[int]]:
    """Indices of frames (images of ``shapes``) in batches for the victim: consecutive ones of equal shape,
    at most ``size`` per batch (the run's ``victim_batch``)."""
    out: list[list[int]] = []
    for i, shape in enumerate(shapes):
        if out and len(out[-1]) < size and shapes[out[-1][0]] == shape:
            out[-1].append(i)
        else:
            out.append([i])
    return out


def render_and_grad(ctx: RunContext, position: int, texture: np.ndarray, iteration: int) -> FrameResult:
    """Algorithm 1's inner body for the frame at ``position`` with texture ``texture`` (sRGB H×W×3):
    :func:`render_and_grad_many` of one frame."""
    return render_and_grad_many(ctx, [position], texture, iteration)[0]


def render_and_grad_many(ctx: RunContext, positions: Sequence[int], texture: np.ndarray,
                         iteration: int) -> list[FrameResult]:
    """Algorithm 1's inner body for the frames at ``positions`` with texture ``texture``: each frame
    rendered by the simulator, the victim once per batch of frames (:func:`victim_pass`), then each
    frame's image gradient carried back to the texture. One :class:`FrameResult` per frame, in order;
    a frame's ``timings`` hold its own render and gradient time and its share of its batch's victim pass.

    With ``eot_print`` each frame renders its own print of the texture and the victim sees the frame
    with camera noise (:mod:`undream.attacks.print_capture`, drawn from (seed, iteration, frame)); the
    gradient goes back through both to ``texture``.
    """
    cfg = ctx.config
    n = len(positions)
    indices = [ctx.frame_indices[p] for p in positions]
    seeds = [frame_seed(cfg.seed, iteration, index) for index in indices]
    conditions = [draw_conditions(cfg.eot, cfg.seed, iteration, index) for index in indices]  # None without eot
    prints = [draw_print(getattr(cfg, "eot_print", None), cfg.seed, iteration, index) for index in indices]
    linear, srgb, t_sim, passed, textures = [], [], [], [], []
    for index, seed, cond, draw in zip(indices, seeds, conditions, prints):
        t0 = time.perf_counter()
        textures.append(printed(texture, draw))  # the texture itself without eot_print
        img = ctx.crops.render(index, textures[-1], cfg.sim_spp, seed, conditions=cond)
        t_sim.append(time.perf_counter() - t0)
        linear.append(img)
        noisy, inside = capture_noise(linear_to_srgb(img), draw)
        srgb.append(noisy)
        passed.append(inside)
    losses: list[float] = [math.nan] * n
    g_images: list[np.ndarray] = [np.empty(0)] * n
    preds: list[dict[str, Any]] = [{}] * n
    t_victim = [0.0] * n
    for batch in victim_batches([im.shape for im in srgb], cfg.victim_batch):
        t0 = time.perf_counter()
        values, grads, records = victim_pass(ctx, [positions[i] for i in batch], [srgb[i] for i in batch], iteration)
        share = (time.perf_counter() - t0) / len(batch)
        for i, v, g, r in zip(batch, values, grads, records):
            losses[i], g_images[i], preds[i], t_victim[i] = v, g, r, share
    out = []
    for i, (index, seed, cond) in enumerate(zip(indices, seeds, conditions)):
        t0 = time.perf_counter()
        g_image = g_images[i] if passed[i] is None else g_images[i] * passed[i]  # the noise's clip
        g_linear = ctx.crops.scale_gradient(index, cfg.sim_spp, srgb_encode_grad(linear[i], g_image), cond)
        grad = ctx.gradients.texture_gradient(index, textures[i], g_linear, cfg.grad_spp, iteration, seed, cond)
        grad = texture_vjp(texture, prints[i], grad)
        t_grad = time.perf_counter() - t0
        # A NaN in the victim's image gradient must not hide behind the renderer: Mitsuba's
        # backward pass turns it into zeros, which would pass as a finite frame.
        finite = bool(np.isfinite(g_images[i]).all() and np.isfinite(grad).all()) and math.isfinite(losses[i])
        timings = {"sim_render": t_sim[i], "victim": t_victim[i], "grad_render": t_grad,
                   "total": t_sim[i] + t_victim[i] + t_grad}
        out.append(FrameResult(grad, losses[i], finite, preds[i], timings))
    return out
