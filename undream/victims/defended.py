"""A defended victim: a chain of input transforms in front of any victim (transform → victim).

:class:`DefendedVictim` is a :class:`~undream.victims.base.Victim` that wraps another: each call
transforms the sRGB [0, 1] ``B×3×H×W`` frames as its :class:`undream.spec.defence.DefenceConfig`
says (:mod:`undream.victims.defences`) and hands them to the inner victim, whose preprocessing,
losses and predictions it reuses. A transform that moves pixels (resize_pad) maps each target's box
onto the transformed frame for the loss and each predicted box back onto the frame given, so a
detector's boxes stay in the input's pixels.

Random transforms are drawn per image from a key: ``(seed, iteration, frame)`` when the caller names
the frames (:meth:`DefendedVictim.for_frames`: the attack's frame jobs), else ``(seed, digest of
the image's 8-bit content)`` (the evaluation, ``predict``): the same frame draws the same transform
whatever batch it is in, and nothing is drawn from a global generator. With ``draws`` > 1 each
frame's loss is the mean over that many draws (EOT).

:func:`defend` wraps a victim as a run config says; :func:`attacker_view` is the victim an attack
differentiates: the defended one (``adaptive``, the default) or the inner one (``adaptive: false``,
the attack ignores the defence), while the evaluation always judges the defended one.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import torch

from undream.errors import VictimError
from undream.spec.defence import DefenceConfig
from undream.victims.base import Target, Victim, check_images
from undream.victims.defences import Key, apply_step, content_key, draw_resize_pad

Affine = tuple[float, float, float, float]  # (sx, sy, tx, ty): a point (x, y) goes to (x sx + tx, y sy + ty)
IDENTITY: Affine = (1.0, 1.0, 0.0, 0.0)


def _compose(first: Affine, then: Affine) -> Affine:
    sx, sy, tx, ty = first
    ux, uy, vx, vy = then
    return sx * ux, sy * uy, tx * ux + vx, ty * uy + vy


def _box_onto(target: Target, a: Affine) -> Target:
    """``target`` with its box (input pixels) mapped onto the transformed frame."""
    if target.box is None or a == IDENTITY:
        return target
    sx, sy, tx, ty = a
    x0, y0, x1, y1 = target.box
    return dataclasses.replace(target, box=(x0 * sx + tx, y0 * sy + ty, x1 * sx + tx, y1 * sy + ty))


def _boxes_back(pred: Any, a: Affine) -> Any:
    """A prediction with its boxes (transformed frame's pixels) mapped back to the input's pixels."""
    if a == IDENTITY or not hasattr(pred, "boxes") or not dataclasses.is_dataclass(pred):
        return pred
    sx, sy, tx, ty = a
    boxes = torch.as_tensor(pred.boxes)
    scale = torch.tensor([sx, sy, sx, sy], dtype=boxes.dtype)
    shift = torch.tensor([tx, ty, tx, ty], dtype=boxes.dtype)
    return dataclasses.replace(pred, boxes=(boxes - shift) / scale)


class DefendedVictim(Victim):
    """``inner`` behind the defence ``config`` (see the module docstring). ``seed``: the run's seed,
    which content-keyed draws use; ``keys``: one draw key per image of the next calls
    (:meth:`for_frames`), or None."""

    def __init__(self, inner: Victim, config: DefenceConfig, seed: int = 0,
                 keys: Sequence[Key] | None = None) -> None:
        if isinstance(inner, DefendedVictim):
            raise VictimError(f"victim {inner.name!r}: is defended already ({inner.defence.label})")
        if not isinstance(config, DefenceConfig):
            raise VictimError(f"defence: must be a DefenceConfig, got {type(config).__name__}")
        super().__init__(inner.name, inner.labels, inner.preprocess_config, inner.device)
        self.inner = inner
        self.defence = config
        self.seed = int(seed)
        self.keys = None if keys is None else tuple(tuple(int(v) for v in k) for k in keys)

    @property  # type: ignore[override]
    def task(self) -> str:  # type: ignore[override]
        return self.inner.task

    @property  # type: ignore[override]
    def loss_kinds(self) -> tuple[str, ...]:  # type: ignore[override]
        return self.inner.loss_kinds

    def for_frames(self, seed: int, iteration: int, frames: Sequence[int]) -> "DefendedVictim":
        """This victim drawing image ``i``'s random transforms from ``(seed, iteration, frames[i])``."""
        return DefendedVictim(self.inner, self.defence, self.seed, [(seed, iteration, f) for f in frames])

    def _draw_keys(self, images: torch.Tensor, draws: int) -> list[Key]:
        """One key per image of ``images`` repeated ``draws`` times (draw-major)."""
        if not self.defence.random:
            return []
        if self.keys is None:
            base = [content_key(self.seed, im) for im in images]
        elif len(self.keys) != images.shape[0]:
            raise VictimError(f"defence: {len(self.keys)} frame keys for {images.shape[0]} images")
        else:
            base = list(self.keys)
        return [(*k, d) for d in range(draws) for k in base]

    def transform(self, images: torch.Tensor, draws: int = 1) -> tuple[torch.Tensor, list[Affine]]:
        """``images`` (sRGB [0, 1], ``B×3×H×W``), repeated ``draws`` times (draw-major: image ``i`` of
        draw ``d`` is row ``d·B + i``), through the defence, differentiated as its ``backward`` says;
        and each row's :data:`Affine` from input pixels to the transformed frame's."""
        check_images(images)
        x = images.repeat(draws, 1, 1, 1) if draws > 1 else images
        keys = self._draw_keys(images, draws)
        affines = [IDENTITY] * x.shape[0]
        for i, step in enumerate(self.defence.steps):
            drawn = None
            if step.random:
                h, w = x.shape[2], x.shape[3]
                drawn = [draw_resize_pad(step, (*k, i), h, w) for k in keys]
                affines = [_compose(a, d.affine(h, w)) for a, d in zip(affines, drawn)]
            x = apply_step(step, x, self.defence.backward, drawn)
        return x, affines

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        return self.inner.preprocess(self.transform(images)[0])

    def forward_raw(self, images: torch.Tensor) -> Any:
        return self.inner.forward_raw(self.transform(images)[0])

    def predict(self, images: torch.Tensor, **options: Any) -> list[Any]:
        """The inner victim's predictions (``options``: its own, e.g. a detector's ``threshold``) on the
        transformed frames (one draw), boxes in ``images``' pixels."""
        with torch.no_grad():
            x, affines = self.transform(images)
            return [_boxes_back(p, a) for p, a in zip(self.inner.predict(x, **options), affines)]

    def losses(self, images: torch.Tensor, target: "Target | Sequence[Target]", kind: str) -> torch.Tensor:
        """``B`` losses: each frame's mean over the defence's ``draws`` of the inner victim's loss on it transformed."""
        targets = self._checked(images, target, kind)
        n = self.defence.draws
        x, affines = self.transform(images, n)
        per = self.inner.losses(x, [_box_onto(t, a) for t, a in zip(targets * n, affines)], kind)
        return per.view(n, -1).mean(0)

    def loss_and_predict(self, images: torch.Tensor, target: "Target | Sequence[Target]",
                         kind: str) -> tuple[torch.Tensor, list[Any]]:
        """:meth:`losses` and the predictions of the first draw, from one pass of the inner victim."""
        targets = self._checked(images, target, kind)
        n, b = self.defence.draws, images.shape[0]
        x, affines = self.transform(images, n)
        per, preds = self.inner.loss_and_predict(x, [_box_onto(t, a) for t, a in zip(targets * n, affines)], kind)
        return per.view(n, -1).mean(0), [_boxes_back(p, a) for p, a in zip(preds[:b], affines[:b])]

    def _losses_from(self, raw: Any, images: torch.Tensor, targets: list[Target], kind: str) -> torch.Tensor:
        x, affines = self.transform(images)  # the draws forward_raw made: they depend on the keys and images only
        return self.inner._losses_from(raw, x, [_box_onto(t, a) for t, a in zip(targets, affines)], kind)

    def _predictions_from(self, raw: Any, images: torch.Tensor) -> list[Any]:
        x, affines = self.transform(images)
        return [_boxes_back(p, a) for p, a in zip(self.inner._predictions_from(raw, x), affines)]

    def __repr__(self) -> str:
        return f"DefendedVictim({self.inner!r}, defence={self.defence.label!r}, backward={self.defence.backward!r})"


def defend(victim: Victim, config: DefenceConfig | None, seed: int = 0) -> Victim:
    """``victim`` behind ``config`` (None: ``victim`` itself); a victim defended already is re-wrapped
    around its inner victim, never twice."""
    if isinstance(victim, DefendedVictim):
        victim = victim.inner
    return victim if config is None else DefendedVictim(victim, config, seed)


def attacker_view(victim: Victim, seed: int | None = None, iteration: int | None = None,
                  frames: Sequence[int] | None = None) -> Victim:
    """The victim an attack differentiates: ``victim`` itself when it is not defended; a defended
    victim's inner one when its defence is not adaptive; else the defended victim, drawing from
    ``(seed, iteration, frames[i])`` when all three are given (content-keyed otherwise)."""
    if not isinstance(victim, DefendedVictim):
        return victim
    if not victim.defence.adaptive:
        return victim.inner
    if seed is None or iteration is None or frames is None:
        return victim
    return victim.for_frames(seed, iteration, frames)
