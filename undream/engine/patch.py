"""The usual pipeline, as a baseline: a flat patch optimised on the images, then worn as the texture.

Physical-attack papers often optimise a patch in image space, pasted over
the object's screen footprint (here: the patch resized into the bounding box
of the object's visibility mask and kept inside the mask), and then put the
patch on the object. This reproduces that on a run's attacked frames, with
the run's victim, loss, budget (L∞ ε around the starting texture, 0–255
sRGB units), PGD step and number of victim evaluations (steps × attacked
frames), starting from the run's starting texture; then it judges the patch
where it will live: as the object's texture, rendered by the simulator, on
the attacked and the held-out frames (:func:`evaluate_texture`).

Images and the patch are sRGB in [0, 1]; the patch has the texture's shape
(H_t×W_t×3) so that it can be worn as the texture as it is.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from undream.color import linear_to_srgb
from undream.engine.context import RunContext
from undream.engine.algorithm import captured_frames, judge, predict, quantise, render_frames
from undream.engine.job import frame_seed
from undream.errors import SpecError
from undream.scenedir.verify import mask_box, read_mask
from undream.victims.defended import attacker_view


@dataclass(frozen=True)
class Footprint:
    """Where frame ``position``'s object is on screen: its mask (H×W bool) and the mask's box (pixels)."""

    position: int
    mask: np.ndarray
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 (x1, y1 exclusive)


def paste(image: Any, patch: Any, footprint: Footprint) -> Any:
    """``image`` (3×H×W torch, sRGB) with ``patch`` (3×H_t×W_t) resized bilinearly into the footprint's
    box and kept inside its mask; differentiable in ``patch``."""
    import torch
    import torch.nn.functional as F

    x0, y0, x1, y1 = footprint.box
    resized = F.interpolate(patch[None], size=(y1 - y0, x1 - x0), mode="bilinear", align_corners=False)[0]
    canvas = torch.zeros_like(image)
    canvas[:, y0:y1, x0:x1] = resized
    mask = torch.from_numpy(footprint.mask.astype(np.float32))[None]
    return image * (1 - mask) + canvas * mask


def footprints(ctx: RunContext, positions: Sequence[int]) -> list[Footprint]:
    """The object's footprint in each frame at ``positions`` where it is visible (from the scene's masks)."""
    out = []
    for p in positions:
        mask = read_mask(ctx.scene_dir, ctx.frame_indices[p])
        box = mask_box(mask)
        if box is not None:
            out.append(Footprint(p, mask, tuple(int(v) for v in box)))  # type: ignore[arg-type]
    if not out:
        raise SpecError("the object is visible in none of the attacked frames: no footprint to paste a patch on")
    return out


def check_attack(attack: Any) -> None:
    """The baseline steps a patch with the run's PGD (its ε, step size and steps); other attacks are refused."""
    from undream.attacks.pgd import PGD

    if not isinstance(attack, PGD):
        raise SpecError(f"attack.name: the pasted-patch baseline runs PGD, got {attack.config.name!r}")


def benign_frames(ctx: RunContext, positions: Sequence[int], texture0: np.ndarray) -> list[tuple[Footprint, Any]]:
    """Each visible frame at ``positions``: its footprint and its benign render with ``texture0``
    (3×H×W torch, sRGB, at ``sim_spp`` with the seed of iteration 0), rendered once."""
    import torch

    cfg = ctx.config
    out = []
    for f in footprints(ctx, positions):
        index = ctx.frame_indices[f.position]
        image = linear_to_srgb(ctx.sim.render(index, texture0, cfg.sim_spp, frame_seed(cfg.seed, 0, index)))
        out.append((f, torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))))
    return out


def _tensor(texture: np.ndarray) -> Any:
    import torch

    return torch.from_numpy(np.ascontiguousarray(texture.transpose(2, 0, 1))).float()


def optimise_patch(ctx: RunContext, frames: Sequence[tuple[Footprint, Any]], texture0: np.ndarray,
                   progress: Any = None) -> tuple[np.ndarray, list[float]]:
    """PGD on a patch pasted into ``frames`` (:func:`benign_frames`); the patch (H_t×W_t×3 sRGB) and
    the mean loss per step. The run's attack must be PGD (its ε, step size and steps are used)."""
    import torch

    from undream.attacks.pgd import pgd_step

    check_attack(ctx.attack)
    targets = [ctx.targets[f.position] for f, _ in frames]
    P0 = _tensor(texture0)
    P, history = P0.clone(), []
    for _ in range(ctx.attack.config.steps):
        P.requires_grad_(True)
        batch = torch.stack([paste(image, P, f) for f, image in frames])
        loss = attacker_view(ctx.victim).loss(batch, targets, ctx.config.loss)
        (G,) = torch.autograd.grad(loss, P)
        history.append(float(loss.detach()))
        with torch.no_grad():
            P = pgd_step(P.detach(), G, P0, ctx.attack.eps, ctx.attack.step_size)
        if progress is not None:
            progress.update(1)
    return P.detach().numpy().transpose(1, 2, 0).astype(np.float32), history


def judge_pasted(ctx: RunContext, frames: Sequence[tuple[Footprint, Any]], patch: np.ndarray) -> dict[str, Any]:
    """What the image-space pipeline itself reports: the victim on ``frames`` with ``patch`` pasted."""
    import torch

    P = _tensor(patch)
    preds: list[Any] = [None] * len(ctx.sequence.frames)
    with torch.no_grad():
        for f, image in frames:
            preds[f.position] = ctx.victim.predict(paste(image, P, f)[None])[0]
    positions = [f.position for f, _ in frames]
    judged = judge(ctx, preds, positions)
    return {"frames": [ctx.frame_indices[p] for p in positions], "metric": judged["metric"],
            "value": judged["value"]}


def evaluate_texture(ctx: RunContext, texture: np.ndarray, splits: dict[str, list[int]]) -> dict[str, Any]:
    """Render every frame with ``texture`` quantised to 8 bits (eval_spp) and judge each split of positions."""
    return judge_splits(ctx, texture_predictions(ctx, texture), splits)


def texture_predictions(ctx: RunContext, texture: np.ndarray, capture: Any = None) -> list[Any]:
    """The victim's prediction on every frame (by position) rendered with ``texture`` quantised to 8 bits;
    with ``capture`` (a :class:`undream.spec.physical.PrintEotConfig`) printed and captured as one
    evaluation draw per frame (:func:`undream.engine.algorithm.captured_frames`)."""
    texture = quantise(texture)
    images = render_frames(ctx, texture, None) if capture is None else captured_frames(ctx, texture, capture)
    return predict(ctx, images)


def judge_splits(ctx: RunContext, preds: Sequence[Any], splits: dict[str, list[int]]) -> dict[str, Any]:
    """Each non-empty split of positions judged from the predictions ``preds`` (by position)."""
    out = {}
    for name, positions in splits.items():
        if positions:
            judged = judge(ctx, preds, positions)
            out[name] = {"frames": [ctx.frame_indices[p] for p in positions], "metric": judged["metric"],
                         "value": judged["value"]}
    return out
