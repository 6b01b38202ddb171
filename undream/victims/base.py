"""The victim protocol: what every model adapter offers the attack.

Images in are sRGB values in [0, 1], ``B×3×H×W`` float torch tensors (a
simulator frame as rendered). A victim

- preprocesses them differentiably (:meth:`Victim.preprocess`),
- runs its model (:meth:`Victim.forward_raw`),
- predicts (:meth:`Victim.predict`): labels or boxes in the input's pixels,
- and gives a task loss per image (:meth:`Victim.losses`; :meth:`Victim.loss`
  is their mean) that the attack MAXIMISES: larger means a more successful
  attack. :meth:`Victim.loss_and_predict` gives both from one forward pass.

A concrete victim implements :meth:`~Victim.forward_raw` and turns its raw
output into per-image losses (``_losses_from``) and predictions
(``_predictions_from``); every public method goes through those two.

Concrete victims: :class:`undream.victims.classifier.Classifier` and
:class:`undream.victims.detector.Detector` wrap any ``torch.nn.Module``; the
Hugging Face adapters subclass them.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Sequence

import torch

from undream.errors import VictimError
from undream.victims.preprocess import PreprocessConfig, preprocess_images

TASKS = ("classification", "detection")
RANGE_SLACK = 1e-4


def check_images(images: Any, name: str = "images") -> None:
    """Raise :class:`VictimError` unless ``images`` is a finite float ``B×3×H×W``
    tensor with values in [0, 1] (``RANGE_SLACK`` either side allowed)."""
    if not isinstance(images, torch.Tensor):
        raise VictimError(f"{name}: must be a torch.Tensor B×3×H×W of sRGB values in [0, 1], "
                          f"got {type(images).__name__}")
    if not images.is_floating_point():
        raise VictimError(f"{name}: must be a float tensor of sRGB values in [0, 1], got dtype "
                          f"{images.dtype} (divide 8-bit images by 255)")
    shape = tuple(images.shape)
    if images.ndim != 4 or shape[1] != 3 or min(shape) == 0:
        raise VictimError(f"{name}: must have shape B×3×H×W (RGB, channels first, batch first), "
                          f"got {shape}")
    with torch.no_grad():
        bad = int((~torch.isfinite(images)).sum())
        if bad:
            raise VictimError(f"{name}: must be finite, got {bad} NaN or infinite values")
        lo, hi = float(images.min()), float(images.max())
    if lo < -RANGE_SLACK or hi > 1 + RANGE_SLACK:
        raise VictimError(f"{name}: values must be sRGB in [0, 1], got range [{lo:.4g}, {hi:.4g}]"
                          + (" (0-255 values? divide by 255)" if hi > 2 else ""))


def _class_id(field: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise VictimError(f"target.{field}: must be a class id (int >= 0), got {value!r}")
    return value


@dataclass(frozen=True)
class Target:
    """What an attack aims at, for one image.

    label: the object's true class id.
    target_label: the class a targeted attack pushes towards, or None.
    box: the object's true box, ``(x0, y0, x1, y1)`` in pixels of the INPUT
        image (before preprocessing), or None. Detection losses use it to pick
        the queries that are the object; the box loss needs it.
    """

    label: int
    target_label: int | None = None
    box: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        _class_id("label", self.label)
        if self.target_label is not None:
            _class_id("target_label", self.target_label)
        if self.box is not None:
            b = self.box
            if (isinstance(b, (str, bytes)) or not hasattr(b, "__len__") or len(b) != 4
                    or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                           for v in b)):
                raise VictimError(f"target.box: must be 4 finite numbers (x0, y0, x1, y1) in "
                                  f"pixels, got {b!r}")
            if not (b[2] > b[0] and b[3] > b[1]):
                raise VictimError(f"target.box: must have x1 > x0 and y1 > y0, got {tuple(b)}")
            object.__setattr__(self, "box", tuple(float(v) for v in b))


@dataclass(frozen=True)
class ClassPrediction:
    """A classifier's prediction for one image: ``label`` id and ``probs`` (C,)."""

    label: int
    probs: torch.Tensor

    def to_dict(self, labels: Sequence[str] | None = None) -> dict[str, Any]:
        out: dict[str, Any] = {"label": self.label, "score": float(self.probs[self.label])}
        if labels is not None:
            out["name"] = labels[self.label]
        return out


@dataclass(frozen=True)
class DetPrediction:
    """A detector's prediction for one image, after the score threshold.

    boxes: ``N×4`` xyxy in pixels of the INPUT image; scores: ``N``; labels: ``N``
    class ids. Sorted by decreasing score. Tensors are detached, on the CPU.
    """

    boxes: torch.Tensor
    scores: torch.Tensor
    labels: torch.Tensor

    def to_dict(self) -> dict[str, Any]:
        return {"boxes": self.boxes.tolist(), "scores": self.scores.tolist(),
                "labels": self.labels.tolist()}


class Victim(ABC):
    """A perception model under attack. See the module docstring.

    Attributes: ``name`` (where it came from), ``task`` (``classification`` or
    ``detection``), ``labels`` (class names, index = class id),
    ``loss_kinds`` (the kinds :meth:`losses` accepts), ``preprocess_config``,
    ``device``.
    """

    task: ClassVar[str]
    loss_kinds: ClassVar[tuple[str, ...]]

    def __init__(self, name: str, labels: Sequence[str], preprocess: PreprocessConfig,
                 device: str | torch.device = "cpu") -> None:
        if not labels:
            raise VictimError(f"victim {name!r}: has no class labels")
        self.name = name
        self.labels = [str(x) for x in labels]
        self.preprocess_config = preprocess
        self.device = _device(device)

    @property
    def num_classes(self) -> int:
        return len(self.labels)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """Check ``images`` (sRGB [0, 1], ``B×3×H×W``), move them to the victim's
        device and preprocess them differentiably into model input."""
        check_images(images)
        return preprocess_images(images.to(self.device), self.preprocess_config)

    @abstractmethod
    def forward_raw(self, images: torch.Tensor) -> Any:
        """The model's raw output for sRGB [0, 1] ``images`` (differentiable)."""

    def predict(self, images: torch.Tensor) -> list[Any]:
        """One prediction per image (no gradient)."""
        with torch.no_grad():
            return self._predictions_from(self.forward_raw(images), images)

    def losses(self, images: torch.Tensor, target: "Target | Sequence[Target]",
               kind: str) -> torch.Tensor:
        """``B`` attack losses of ``kind``, one per image (differentiable); larger =
        more successful.

        ``target`` is one :class:`Target` for every image or one per image.
        """
        targets = self._checked(images, target, kind)
        return self._losses_from(self.forward_raw(images), images, targets, kind)

    def loss(self, images: torch.Tensor, target: "Target | Sequence[Target]",
             kind: str) -> torch.Tensor:
        """Scalar attack loss: the mean over the images of :meth:`losses`."""
        return self.losses(images, target, kind).mean()

    def loss_and_predict(self, images: torch.Tensor, target: "Target | Sequence[Target]",
                         kind: str) -> tuple[torch.Tensor, list[Any]]:
        """:meth:`losses` and :meth:`predict` of ``images`` from ONE forward pass.

        The ``B`` losses carry the gradient; the predictions are those of
        :meth:`predict` (default settings), computed from the same raw output
        without gradient.
        """
        targets = self._checked(images, target, kind)
        raw = self.forward_raw(images)
        per_image = self._losses_from(raw, images, targets, kind)
        with torch.no_grad():
            preds = self._predictions_from(raw, images)
        return per_image, preds

    @abstractmethod
    def _losses_from(self, raw: Any, images: torch.Tensor, targets: list[Target],
                     kind: str) -> torch.Tensor:
        """``B`` losses of checked ``kind`` and ``targets`` from ``raw`` = ``forward_raw(images)``."""

    @abstractmethod
    def _predictions_from(self, raw: Any, images: torch.Tensor) -> list[Any]:
        """One prediction per image from ``raw`` = ``forward_raw(images)``; called without gradient."""

    def _checked(self, images: torch.Tensor, target: Any, kind: str) -> list[Target]:
        """The per-image targets, after checking ``kind``, ``images`` and ``target``."""
        if kind not in self.loss_kinds:
            raise VictimError(f"loss kind {kind!r}: victim {self.name!r} does {self.task}; "
                              f"valid kinds are {', '.join(self.loss_kinds)}")
        check_images(images)
        return self._targets(target, images.shape[0])

    def _targets(self, target: Any, batch: int) -> list[Target]:
        targets = [target] * batch if isinstance(target, Target) else list(target)
        if len(targets) != batch or not all(isinstance(t, Target) for t in targets):
            raise VictimError(f"target: must be a Target or {batch} Targets (one per image), "
                              f"got {target!r}")
        for t in targets:
            for field, v in (("label", t.label), ("target_label", t.target_label)):
                if v is not None and v >= self.num_classes:
                    raise VictimError(f"target.{field}: {v} is not a class of victim {self.name!r} "
                                      f"(ids 0..{self.num_classes - 1})")
        return targets

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(name={self.name!r}, task={self.task!r}, "
                f"classes={self.num_classes}, device={str(self.device)!r})")


def _device(device: str | torch.device) -> torch.device:
    try:
        return torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise VictimError(f"device: {device!r} is not a torch device ({err})") from None


def require_target_label(targets: list[Target], kind: str) -> torch.Tensor:
    """The targets' ``target_label`` as a long tensor; error if any is missing."""
    if any(t.target_label is None for t in targets):
        raise VictimError(f"loss kind {kind!r}: needs Target.target_label (the class to push "
                          f"towards), got {[t.target_label for t in targets]}")
    return torch.tensor([t.target_label for t in targets], dtype=torch.long)
