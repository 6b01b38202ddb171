"""A dense (one-stage, YOLO-style) object detector victim around any ``torch.nn.Module``.

The module takes preprocessed ``B×3×h×w`` input and returns one candidate per
cell of its feature maps, in one of two layouts (``output_format``):

- ``native`` (:class:`undream.victims.yolo.YoloNet`): ``B×N×(4 + C)``, the box
  as xyxy pixels of the model input, then C class LOGITS;
- ``ultralytics`` (YOLOv8, YOLO11 ``DetectionModel`` in eval mode): ``B×(4 +
  C)×N`` (or a tuple whose first item is that), the box as centre x, centre
  y, width, height in pixels of the model input, then C class PROBABILITIES
  (sigmoid already applied).

Both decode to :class:`DenseOutput`. The losses are the DETR ones of
:mod:`undream.victims.losses` on the candidates BEFORE NMS, weighted by
:func:`undream.victims.losses.dense_weights`; predictions are the candidates
after a score threshold and class-aware NMS (:mod:`undream.victims.nms`).
Preprocessing must only resize (no crop), so boxes scale back to the input.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch

from undream.errors import VictimError
from undream.victims import losses
from undream.victims.base import DetPrediction
from undream.victims.detector import Detector
from undream.victims.nms import select_detections
from undream.victims.preprocess import PreprocessConfig
from undream.victims.yolo import STRIDES, anchor_points

FORMATS = ("native", "ultralytics")
LOG_EPS = 1e-12  # probabilities (ultralytics) are clamped to this before their log


@dataclass(frozen=True)
class DenseOutput:
    """Decoded candidates: ``boxes`` ``B×N×4`` xyxy pixels of the model input,
    ``log_probs`` ``B×N×C`` log class scores, ``size`` the model input's (h, w)
    and ``points`` ``N×2`` each candidate's cell centre (x, y pixels), or None
    where the layout of the candidates is unknown."""

    boxes: torch.Tensor
    log_probs: torch.Tensor
    size: tuple[int, int]
    points: torch.Tensor | None

    @property
    def scale(self) -> torch.Tensor:
        h, w = self.size
        return torch.tensor([w, h, w, h], dtype=self.boxes.dtype, device=self.boxes.device)

    @property
    def boxes_xyxy(self) -> torch.Tensor:
        """``B×N×4`` normalised xyxy (fractions of the input width and height)."""
        return self.boxes / self.scale

    @property
    def points_norm(self) -> torch.Tensor | None:
        """``N×2`` cell centres as fractions of the input width and height."""
        return None if self.points is None else self.points / self.scale[:2]


def decode_native(out: torch.Tensor, classes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``B×N×(4 + C)`` (xyxy pixels, logits) → boxes ``B×N×4`` and log-sigmoid scores ``B×N×C``."""
    if out.ndim != 3 or out.shape[-1] != 4 + classes:
        raise VictimError(f"dense output (native): must be B×N×(4 + {classes}) (xyxy pixels and "
                          f"{classes} class logits per candidate), got {tuple(out.shape)}")
    return out[..., :4], torch.nn.functional.logsigmoid(out[..., 4:])


def decode_ultralytics(out: torch.Tensor, classes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``B×(4 + C)×N`` (cxcywh pixels, probabilities) → boxes ``B×N×4`` xyxy and log scores ``B×N×C``."""
    if out.ndim != 3 or out.shape[1] != 4 + classes:
        raise VictimError(f"dense output (ultralytics): must be B×(4 + {classes})×N (centre-xywh "
                          f"pixels and {classes} class probabilities per candidate), got "
                          f"{tuple(out.shape)} (an end-to-end head's B×300×6 is not supported)")
    t = out.transpose(1, 2)
    return losses.cxcywh_to_xyxy(t[..., :4]), t[..., 4:].clamp(min=LOG_EPS).log()


DECODERS = {"native": decode_native, "ultralytics": decode_ultralytics}


class DenseDetector(Detector):
    """Dense detection victim: the :class:`Detector` losses (``vanish``,
    ``mislabel``, ``box``) on the candidates before NMS, weighted by
    :func:`losses.dense_weights` (``min_iou``); predictions after NMS.

    ``score_threshold``, ``iou_threshold`` (NMS), ``max_detections`` apply to
    :meth:`predict` only; ultralytics' own defaults are 0.25, 0.7 and 300.
    ``strides``: the levels' strides, for the candidates' cell centres.
    """

    def __init__(self, module: torch.nn.Module, labels: Sequence[str],
                 preprocess: PreprocessConfig | None = None, name: str = "torch",
                 device: str | torch.device = "cpu", output_format: str = "native",
                 strides: Sequence[int] = STRIDES, score_threshold: float = 0.25,
                 iou_threshold: float = 0.7, max_detections: int = 100, min_iou: float = 0.3,
                 vanish_reduce: str = "mean") -> None:
        if output_format not in FORMATS:
            raise VictimError(f"victim {name!r}: output_format must be one of {', '.join(FORMATS)}, "
                              f"got {output_format!r}")
        for field, v in (("iou_threshold", iou_threshold), ("min_iou", min_iou)):
            if not 0.0 <= float(v) <= 1.0:
                raise VictimError(f"victim {name!r}: {field} must be in [0, 1], got {v!r}")
        if isinstance(max_detections, bool) or not isinstance(max_detections, int) or max_detections < 1:
            raise VictimError(f"victim {name!r}: max_detections must be an integer >= 1, got {max_detections!r}")
        super().__init__(module, labels, preprocess, name, device, "sigmoid", score_threshold, vanish_reduce)
        self.output_format = output_format
        self.strides = tuple(int(s) for s in strides)
        self.iou_threshold = float(iou_threshold)
        self.max_detections = max_detections
        self.min_iou = float(min_iou)

    def forward_raw(self, images: torch.Tensor) -> DenseOutput:  # type: ignore[override]
        """Decoded candidates for sRGB [0, 1] images (differentiable)."""
        x = self.preprocess(images)
        out = self.module(x)
        if isinstance(out, (tuple, list)) and out:  # ultralytics in eval mode: (y, feature maps)
            out = out[0]
        if not isinstance(out, torch.Tensor):
            raise VictimError(f"victim {self.name!r}: model output must be a tensor of candidates "
                              f"({self.output_format} layout), got {type(out).__name__}")
        boxes, log_probs = DECODERS[self.output_format](out, self.num_classes)
        if boxes.shape[0] != images.shape[0]:
            raise VictimError(f"victim {self.name!r}: {boxes.shape[0]} outputs for {images.shape[0]} images")
        h, w = x.shape[-2:]
        points, _ = anchor_points(h, w, self.strides, boxes.device)
        return DenseOutput(boxes, log_probs, (h, w), points if len(points) == boxes.shape[1] else None)

    def predict(self, images: torch.Tensor, threshold: float | None = None) -> list[DetPrediction]:
        """Per image: the candidates scoring at least ``threshold`` (default
        ``score_threshold``) after class-aware NMS; boxes xyxy in pixels of the
        input image, sorted by decreasing score."""
        with torch.no_grad():
            return self._predictions_from(self.forward_raw(images), images, threshold)

    def _predictions_from(self, raw: DenseOutput, images: torch.Tensor,  # type: ignore[override]
                          threshold: float | None = None) -> list[DetPrediction]:
        thr = self.score_threshold if threshold is None else float(threshold)
        h, w = images.shape[-2:]
        scale = torch.tensor([w, h, w, h], dtype=torch.float32)
        boxes = raw.boxes_xyxy.float().cpu() * scale
        probs = self._candidate_probs(raw)
        return [DetPrediction(*select_detections(b, p, thr, self.iou_threshold, self.max_detections))
                for b, p in zip(boxes, probs)]

    def _candidate_probs(self, raw: DenseOutput) -> torch.Tensor:
        """``B×N×C`` class probabilities (CPU) of the candidates predictions may keep; a subclass may
        zero some (CenterNet keeps the peaks of its heat maps)."""
        return raw.log_probs.float().exp().cpu()

    def _object_weights(self, raw: Any, labels: torch.Tensor,
                        true_boxes: torch.Tensor | None) -> torch.Tensor:
        """``B×N`` weights of the candidates that are the object: :func:`losses.dense_weights`."""
        return losses.dense_weights(raw.log_probs, raw.boxes_xyxy, labels, true_boxes,
                                    raw.points_norm, self.min_iou)
