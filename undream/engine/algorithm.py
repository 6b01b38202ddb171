"""Algorithm 1, stage by stage, in the order a run goes through them, without store or broker.

Every caller goes through these functions: the farm's stages (:mod:`scheduler.stages`: start, the
per-frame batches, collect; :mod:`scheduler.iteration`: the frame job and the reduce-and-step
callback; :mod:`scheduler.evaluation`: the evaluation's frame jobs), ``undream run`` (the same stages
drained in one process), the pasted-patch baseline and the study scripts. Around them the scheduler
only reads and writes run state.

1. **start**: :func:`start_texture` (T0, the scene's texture) and :func:`visibility` (the texels some
   frame sees, for a random start and the report);
2. **plan**: :func:`plan` (the frames of iteration k: all attacked ones or a seeded minibatch);
3. **per-frame job**: :func:`frame_jobs` (simulator render → victim loss → texture gradient, the
   victim once per batch of frames; :func:`frame_job` for one frame);
4. **reduce**: :func:`reduce` (mean gradient and loss over the finite frames, the gradients
   weighted by ``attack.frame_weights``), then :func:`objective` (the run's regularisers subtracted);
5. **step**: :func:`step` (the attack's projected step, then the printer's gamut; :func:`begin` for the start);
6. **evaluate**: :func:`quantise` (the 8-bit texture), :func:`eval_render` per frame,
   :func:`eval_predictions` and :func:`eval_losses` (the victim once per batch of frames;
   :func:`render_frames` and :func:`predict` over a whole sequence), and :func:`judge` (accuracy
   or AP@0.5 over attacked and held-out frames).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch
from PIL import Image

from undream.attacks import average_frames, frame_batch
from undream.attacks.print_capture import capture_noise, draw_print, printed
from undream.attacks.regularise import Regularisers, penalty
from undream.attacks.regularise import objective as regularised
from undream.color import linear_to_srgb, to_uint8
from undream.engine.context import RunContext
from undream.engine import job
from undream.engine.job import FrameResult, class_score, frame_seed, ground_truth, top_detections, truth_box
from undream.metrics import accuracy, average_precision, correct, is_detected
from undream.render.differentiable import texture_gradient
from undream.render.loading import read_texture_srgb
from undream.scene.layout import frame_name
from undream.victims.defended import attacker_view

if TYPE_CHECKING:
    from undream.attacks.base import Attack
    from undream.printing.gamut import Gamut
    from undream.render.scene_cache import SceneCache
    from undream.spec import Frame

EVAL_ITERATION = 10**6  # seeds of evaluation renders never coincide with the attack's
# The evaluation renders' run seed, the same for every run (not the run's seed): the runs of a sweep
# judge their textures on the same render noise, and the benign evaluation is the same work for all of
# them (scheduler.benign computes it once). A run of seed 0 renders as it always did.
EVAL_SEED = 0


# --------------------------------------------------------------------------- 1. start

def start_texture(ctx: RunContext) -> np.ndarray:
    """The scene directory's texture, the attack's T0: sRGB H×W×3 float32 (from the exact float EXR)."""
    return read_texture_srgb(ctx.scenes.mi, ctx.scene_dir / "textures" / f"{ctx.sequence.texture.name}.exr")


def visibility(scenes: "SceneCache", frames: Sequence["Frame"], texture: np.ndarray, spp: int,
               seed: int) -> np.ndarray:
    """Texels some frame sees (H×W bool): a gradient pass per frame seeded with a white image gradient
    at ``spp`` samples per pixel (a run passes its ``grad_spp`` and seed; the report at least 32)."""
    seen = np.zeros(texture.shape[:2], dtype=bool)
    for f in frames:
        res = f.camera.resolution
        g = texture_gradient(scenes, f.index, texture, np.ones((res[1], res[0], 3), np.float32), spp, seed, seed + 1)
        seen |= (g != 0).any(axis=2)
    return seen


# --------------------------------------------------------------------------- 2. plan

def plan(attacked: Sequence[int], frames_per_step: int | None, k: int, seed: int) -> list[int]:
    """The frame positions of iteration ``k``: every attacked position, or ``frames_per_step`` of them
    drawn from (seed, k) only, so a retried iteration draws the same ones; never a held-out frame."""
    return [attacked[i] for i in frame_batch(len(attacked), frames_per_step, k, seed)]


# --------------------------------------------------------------------------- 3. per-frame job

def frame_jobs(ctx: RunContext, positions: Sequence[int], texture: np.ndarray, k: int) -> list[FrameResult]:
    """Frames ``positions`` of iteration ``k`` with texture ``k``: each frame's simulator render at
    ``sim_spp``, the victim's losses and image gradients in one pass per batch of frames
    (``victim_batch``), and each gradient carried back to the texture
    (:func:`undream.engine.job.render_and_grad_many`, where each part is timed)."""
    return job.render_and_grad_many(ctx, positions, texture, k)


def frame_job(ctx: RunContext, position: int, texture: np.ndarray, k: int) -> FrameResult:
    """:func:`frame_jobs` of the one frame ``position``."""
    return frame_jobs(ctx, [position], texture, k)[0]


# --------------------------------------------------------------------------- 4. reduce

def reduce(grads: Sequence[np.ndarray], losses: Sequence[float | None], finite: Sequence[bool],
           weights: str = "mean") -> tuple[torch.Tensor, float, list[int]]:
    """Mean texture gradient (each frame's scaled to a common norm first with ``weights`` ``unit``:
    ``attack.frame_weights``) and mean loss over the frames whose gradient and loss are finite (and
    not recorded otherwise), and the indices of the frames kept; none kept: :class:`AttackError`."""
    values = [float("nan") if v is None else v for v in losses]
    return average_frames([torch.from_numpy(g) for g in grads], values, list(finite), weights=weights)


def objective(config: Any, texture: np.ndarray, grad: torch.Tensor, loss: float,
              state: Any) -> tuple[torch.Tensor, float, dict[str, float]]:
    """The attack's objective at texture ``texture`` (sRGB H×W×3) from the victim's mean gradient and
    loss: ``victim_loss − Σ w_i R_i(T)`` over the run's regularisers (``config.regularise``, a
    :class:`undream.spec.run.RunConfig`), the regularisers' gradient only on texels seen so far
    (``state["visible"]`` and the texels ``grad`` reaches; :func:`undream.attacks.regularise.objective`).
    Returns (G, objective value, named terms for the iteration record: ``loss_victim``, ``loss_total``,
    ``reg_<term>``); without regularisers (grad, loss, {})."""
    seen = state.get("visible") if isinstance(state, dict) else None
    seen = seen if isinstance(seen, torch.Tensor) and seen.shape == grad.shape[:2] else None
    return regularised(Regularisers.of(getattr(config, "regularise", None)), texture, grad, loss, seen)


def objective_value(config: Any, texture: np.ndarray, loss: float) -> float:
    """The objective of :func:`objective` at ``texture`` from the victim's mean ``loss`` there (what an
    attack's final pick compares with the values its steps saw)."""
    return loss - penalty(Regularisers.of(getattr(config, "regularise", None)), texture)


# --------------------------------------------------------------------------- 5. step

def step(attack: "Attack", texture: np.ndarray, grad: torch.Tensor, loss: float,
         state: Any, gamut: "Gamut | None" = None) -> tuple[np.ndarray, Any]:
    """T_{k+1} and the attack's next state: PGD, APGD, MI-FGSM or Adam, projected onto the ε ball
    around T0 and onto [0, 1] (:meth:`undream.attacks.base.Attack.step`), then, with a ``gamut``
    (``RunContext.gamut``, the run's ``gamut``), into the printer's gamut
    (:func:`undream.printing.gamut.project_gamut`; applied after the ε ball, so a printable texture
    wins where the two disagree: a texel may end up to the gamut's move outside the ball)."""
    T_next, state = attack.step(torch.from_numpy(texture), grad, loss, state)
    T_next = T_next.numpy().astype(np.float32)
    return (T_next if gamut is None else gamut.project(T_next)), state


def begin(attack: "Attack", T0: np.ndarray, visible: np.ndarray | None,
          gamut: "Gamut | None" = None) -> tuple[np.ndarray, Any]:
    """The texture the attack evaluates first and its state (:meth:`undream.attacks.base.Attack.start`:
    ``T0`` or a random start among the ``visible`` texels), projected into ``gamut`` when given, as
    every later step is; the state's ε ball stays centred on ``T0`` itself."""
    T, state = attack.start(torch.from_numpy(T0), visible=None if visible is None else torch.from_numpy(visible))
    T = T.numpy().astype(np.float32)
    return (T if gamut is None else gamut.project(T)), state


# --------------------------------------------------------------------------- 6. evaluate

def quantise(texture: np.ndarray) -> np.ndarray:
    """The 8-bit texture a user would print or import into a simulator, back in [0, 1]."""
    return to_uint8(texture).astype(np.float32) / 255.0


def eval_render(ctx: RunContext, position: int, texture: np.ndarray) -> np.ndarray:
    """Frame ``position`` with ``texture`` at ``eval_spp`` and the evaluation's seed (:data:`EVAL_SEED`,
    whatever the run's seed): sRGB H×W×3."""
    index = ctx.frame_indices[position]
    return linear_to_srgb(ctx.sim.render(index, texture, ctx.config.eval_spp,
                                         frame_seed(EVAL_SEED, EVAL_ITERATION, index)))


def _stacks(ctx: RunContext, images: Sequence[np.ndarray]) -> list[tuple[list[int], torch.Tensor]]:
    """The images as victim batches (:func:`undream.engine.job.victim_batches`): (indices, B×3×H×W)."""
    groups = job.victim_batches([im.shape for im in images], ctx.config.victim_batch)
    return [(g, job.stack_images([images[i] for i in g])) for g in groups]


def eval_predictions(ctx: RunContext, images: Sequence[np.ndarray]) -> list[Any]:
    """The victim's prediction on each sRGB frame (a class and its score, or boxes), one pass per batch."""
    out: list[Any] = [None] * len(images)
    with torch.no_grad():
        for group, x in _stacks(ctx, images):
            for i, pred in zip(group, ctx.victim.predict(x)):
                out[i] = pred
    return out


def eval_losses(ctx: RunContext, positions: Sequence[int], images: Sequence[np.ndarray]) -> list[float]:
    """The attack's loss on each frame ``positions[i]`` rendered as ``images[i]`` (APGD's final pick
    reads them), one pass per batch, by the victim the attack sees (a non-adaptive attack's pick
    knows nothing of the defence: :func:`undream.victims.defended.attacker_view`)."""
    out = [float("nan")] * len(images)
    with torch.no_grad():
        for group, x in _stacks(ctx, images):
            values = attacker_view(ctx.victim).losses(x, [ctx.targets[positions[i]] for i in group], ctx.config.loss)
            for i, v in zip(group, values.double().tolist()):
                out[i] = v
    return out


def render_frames(ctx: RunContext, texture: np.ndarray, out_dir: Path | None) -> list[np.ndarray]:
    """:func:`eval_render` of every frame; saved as PNGs when ``out_dir`` is set."""
    images = []
    for position, index in enumerate(ctx.frame_indices):
        img = eval_render(ctx, position, texture)
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(to_uint8(img)).save(out_dir / f"{frame_name('frame', index)}.png")
        images.append(img)
    return images


def captured_frames(ctx: RunContext, texture: np.ndarray, capture: Any) -> list[np.ndarray]:
    """Every frame as :func:`eval_render` renders it, but with ``texture`` printed and the frame
    captured as one draw of ``capture`` (a :class:`undream.spec.physical.PrintEotConfig`) per frame:
    :func:`undream.attacks.print_capture.draw_print` of (the run's seed, :data:`EVAL_ITERATION`, frame
    index), a draw no attack iteration makes, the same for every texture judged."""
    images = []
    for position, index in enumerate(ctx.frame_indices):
        draw = draw_print(capture, ctx.config.seed, EVAL_ITERATION, index)
        images.append(capture_noise(eval_render(ctx, position, printed(texture, draw)), draw)[0])
    return images


def predict(ctx: RunContext, images: list[np.ndarray]) -> list[Any]:
    """:func:`eval_predictions` of the images."""
    return eval_predictions(ctx, images)


def ground_truths(ctx: RunContext) -> list[Any]:
    """The object's box per frame (from its visibility mask); no box where it is unseen."""
    return [ground_truth(t) for t in ctx.targets]


def judge(ctx: RunContext, preds: list[Any], positions: list[int] | None = None) -> dict[str, Any]:
    """Per-frame correctness and the overall measure (accuracy, or AP@0.5 of the object's class)
    over the frames at ``positions`` (default all; ``preds`` holds one prediction per frame).

    A detector's per-frame row also holds ``boxes`` (:func:`undream.engine.job.top_detections`: at most
    the five highest-scoring kept detections) and ``truth_box`` (the object's mask box, x1/y1 exclusive,
    frame pixels; None where it is unseen)."""
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
             "score": round(float(p.scores.max()), 4) if len(p.scores) else 0.0,
             "boxes": top_detections(p, ctx.victim.labels),
             "truth_box": truth_box(ctx.targets[i])}
            for i, f, p, gt in zip(keep, frames, preds, truths)]
    value = average_precision(preds, truths, label) if preds else None
    return {"metric": "ap50", "value": value, "per_frame": rows}
