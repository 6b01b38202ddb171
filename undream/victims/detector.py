"""A DETR-style object detector victim around any ``torch.nn.Module``.

The module takes preprocessed ``B×3×h×w`` input and returns, per image and
query, class logits ``B×Q×K`` and boxes ``B×Q×4`` as normalised
``(cx, cy, w, h)`` in [0, 1] of its input: a ``(logits, boxes)`` tuple, an
object with ``.logits`` and ``.pred_boxes`` (Hugging Face), or a dict with
``pred_logits`` and ``pred_boxes`` (the original DETR code).

``K = C + 1`` (last class "no object") means softmax scoring (DETR, YOLOS);
``K = C`` means one sigmoid per class (Deformable DETR, RT-DETR, ...).
Preprocessing must only resize (no crop), so normalised boxes are the same
fractions of the input image.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence, cast

import torch

from undream.errors import VictimError
from undream.spec.run import TASK_LOSSES
from undream.victims import losses
from undream.victims.base import DetPrediction, Target, Victim, require_target_label
from undream.victims.preprocess import PreprocessConfig

DETECTION_LOSSES = TASK_LOSSES["detection"]  # one list: what a run config accepts


@dataclass(frozen=True)
class DetectionOutput:
    """Raw detector output: ``logits`` ``B×Q×K``, ``boxes`` ``B×Q×4`` normalised
    cxcywh, and how the logits are scored (``softmax`` or ``sigmoid``)."""

    logits: torch.Tensor
    boxes: torch.Tensor
    activation: str

    @property
    def log_probs(self) -> torch.Tensor:
        """``B×Q×C`` log class scores (no-object dropped)."""
        return losses.class_log_probs(self.logits, self.activation)

    @property
    def boxes_xyxy(self) -> torch.Tensor:
        """``B×Q×4`` normalised xyxy (fractions of the input width and height)."""
        return losses.cxcywh_to_xyxy(self.boxes)


def _outputs_of(out: Any) -> tuple[Any, Any]:
    if isinstance(out, dict) and "pred_logits" in out:
        return out["pred_logits"], out.get("pred_boxes")
    if hasattr(out, "logits") and hasattr(out, "pred_boxes"):
        return out.logits, out.pred_boxes
    if isinstance(out, (tuple, list)) and len(out) >= 2:
        return out[0], out[1]
    return out, None


class Detector(Victim):
    """Detection victim. Losses (all maximised by the attack; see
    :mod:`undream.victims.losses` for the formulas):

    - ``vanish``: minus the true class's probability on the object's queries,
    - ``mislabel``: log-probability of ``Target.target_label`` on them,
    - ``box``: L1 + (1 - GIoU) distance of their boxes from ``Target.box``.

    The object's queries are those overlapping ``Target.box`` (IoU-weighted)
    or, without a box, those that find the true class (probability-weighted).
    ``score_threshold`` applies to :meth:`predict` only.
    """

    task = "detection"
    loss_kinds = DETECTION_LOSSES

    def __init__(self, module: torch.nn.Module, labels: Sequence[str],
                 preprocess: PreprocessConfig | None = None, name: str = "torch",
                 device: str | torch.device = "cpu", activation: str = "auto",
                 score_threshold: float = 0.5, vanish_reduce: str = "mean") -> None:
        preprocess = preprocess or PreprocessConfig()
        if preprocess.crop is not None:
            raise VictimError(f"victim {name!r}: a detector's preprocessing must not crop "
                              f"(boxes would not map back to the input), got crop {preprocess.crop}")
        if activation not in ("auto", *losses.ACTIVATIONS):
            raise VictimError(f"victim {name!r}: activation must be auto, softmax or sigmoid, "
                              f"got {activation!r}")
        if not 0.0 <= float(score_threshold) <= 1.0:
            raise VictimError(f"victim {name!r}: score_threshold must be in [0, 1], "
                              f"got {score_threshold!r}")
        if vanish_reduce not in ("mean", "max"):
            raise VictimError(f"victim {name!r}: vanish_reduce must be 'mean' or 'max', "
                              f"got {vanish_reduce!r}")
        super().__init__(name, labels, preprocess, device)
        self.module = module.to(self.device).eval().requires_grad_(False)
        self.activation = activation
        self.score_threshold = float(score_threshold)
        self.vanish_reduce = vanish_reduce

    def forward_raw(self, images: torch.Tensor) -> DetectionOutput:
        """Logits and normalised boxes for sRGB [0, 1] images (differentiable)."""
        logits, boxes = _outputs_of(self.module(self.preprocess(images)))
        b = images.shape[0]
        if (not isinstance(logits, torch.Tensor) or not isinstance(boxes, torch.Tensor)
                or logits.ndim != 3 or boxes.ndim != 3 or logits.shape[0] != b
                or boxes.shape != (*logits.shape[:2], 4)):
            raise VictimError(f"victim {self.name!r}: model output must be class logits B×Q×K and "
                              f"boxes B×Q×4 (DETR style), got {_shapes(logits, boxes)}")
        return DetectionOutput(logits, boxes, self._activation(logits.shape[-1]))

    def _activation(self, k: int) -> str:
        want = {"softmax": self.num_classes + 1, "sigmoid": self.num_classes}
        act = self.activation
        if act == "auto":
            act = "softmax" if k == want["softmax"] else "sigmoid" if k == want["sigmoid"] else ""
        if not act or k != want[act]:
            raise VictimError(f"victim {self.name!r}: logits have {k} classes per query; with "
                              f"{self.num_classes} labels expected {want['softmax']} (softmax "
                              f"with no-object) or {want['sigmoid']} (sigmoid)")
        return act

    def predict(self, images: torch.Tensor, threshold: float | None = None) -> list[DetPrediction]:
        """Per image: each query's best class and score, kept if the score is at
        least ``threshold`` (default ``score_threshold``); boxes in pixels of
        the input image, xyxy, sorted by decreasing score."""
        with torch.no_grad():
            return self._predictions_from(self.forward_raw(images), images, threshold)

    def _predictions_from(self, raw: DetectionOutput, images: torch.Tensor,
                          threshold: float | None = None) -> list[DetPrediction]:
        """:meth:`predict` from ``raw`` = ``forward_raw(images)``."""
        thr = self.score_threshold if threshold is None else float(threshold)
        h, w = images.shape[-2:]
        scale = torch.tensor([w, h, w, h], dtype=torch.float32)
        scores, labels = raw.log_probs.float().exp().max(-1)
        boxes = raw.boxes_xyxy.float().cpu() * scale
        preds = []
        for s, lab, bx in zip(scores.cpu(), labels.cpu(), boxes):
            keep = (s >= thr).nonzero().squeeze(1)
            keep = keep[s[keep].argsort(descending=True)]
            preds.append(DetPrediction(bx[keep], s[keep], lab[keep]))
        return preds

    def _losses_from(self, raw: DetectionOutput, images: torch.Tensor, targets: list[Target],
                     kind: str) -> torch.Tensor:
        """``B`` losses of ``kind`` from ``raw`` = ``forward_raw(images)``."""
        log_probs, boxes = raw.log_probs, raw.boxes_xyxy
        dev = log_probs.device
        y = torch.tensor([t.label for t in targets], dtype=torch.long, device=dev)
        true_boxes = self._true_boxes(targets, images.shape[-2:], kind)
        weights = self._object_weights(raw, y, None if true_boxes is None else true_boxes.to(dev))
        if kind == "vanish":
            return losses.det_vanish(log_probs, y, weights, self.vanish_reduce, reduction="none")
        if kind == "mislabel":
            t = require_target_label(targets, kind).to(dev)
            return losses.det_mislabel(log_probs, t, weights, reduction="none")
        boxes_true = cast(torch.Tensor, true_boxes)  # _true_boxes raised if any was missing
        return losses.det_box(boxes, boxes_true.to(dev, boxes.dtype), weights, reduction="none")

    def _object_weights(self, raw: DetectionOutput, labels: torch.Tensor,
                        true_boxes: torch.Tensor | None) -> torch.Tensor:
        """``B×Q`` weights of the queries that are the object: :func:`losses.match_weights`."""
        return losses.match_weights(raw.log_probs, raw.boxes_xyxy, labels, true_boxes)

    @staticmethod
    def _true_boxes(targets: list[Target], hw: Sequence[int], kind: str) -> torch.Tensor | None:
        """``B×4`` normalised xyxy true boxes, NaN rows where a target has none."""
        if all(t.box is None for t in targets):
            if kind == "box":
                raise VictimError("loss kind 'box': needs Target.box (the object's true box, "
                                  "xyxy pixels of the input image), got None")
            return None
        if kind == "box" and any(t.box is None for t in targets):
            raise VictimError("loss kind 'box': every Target needs a box, got "
                              f"{[t.box for t in targets]}")
        h, w = hw
        nan = (float("nan"),) * 4
        rows = [t.box if t.box is not None else nan for t in targets]
        return torch.tensor(rows, dtype=torch.float32) / torch.tensor([w, h, w, h],
                                                                        dtype=torch.float32)


def _shapes(*xs: Any) -> str:
    return ", ".join(str(tuple(x.shape)) if isinstance(x, torch.Tensor) else type(x).__name__
                     for x in xs)
