"""Non-maximum suppression in plain torch (no torchvision): one function per step.

Boxes are ``N×4`` xyxy in any one unit (pixels here); scores ``N``; labels
``N`` class ids. Suppression is greedy, in decreasing score order, and
class-aware: a box suppresses only later boxes OF ITS CLASS that overlap it at
IoU above the threshold (as YOLOv8's and torchvision's ``batched_nms`` do).
"""
from __future__ import annotations

import torch

from undream.errors import VictimError
from undream.victims.losses import box_iou_giou


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Indices of the boxes kept by greedy NMS, in decreasing score order.

    A box is dropped when a higher-scoring kept box overlaps it at IoU
    ``> iou_threshold``. ``boxes`` ``N×4`` xyxy, ``scores`` ``N``.
    """
    if boxes.ndim != 2 or boxes.shape[-1] != 4 or scores.shape != boxes.shape[:1]:
        raise VictimError(f"nms: boxes must be N×4 and scores N, got {tuple(boxes.shape)} and "
                          f"{tuple(scores.shape)}")
    order = scores.argsort(descending=True)
    iou, _ = box_iou_giou(boxes[order][:, None, :], boxes[order][None, :, :])
    suppressed = torch.zeros(len(order), dtype=torch.bool, device=boxes.device)
    keep = []
    for i in range(len(order)):
        if bool(suppressed[i]):
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return order[torch.tensor(keep, dtype=torch.long, device=boxes.device)]


def batched_nms(boxes: torch.Tensor, scores: torch.Tensor, labels: torch.Tensor,
                iou_threshold: float) -> torch.Tensor:
    """Class-aware :func:`nms`: boxes of different ``labels`` never suppress each other.

    Each class's boxes are shifted by a distinct offset larger than every
    coordinate, so that boxes of two classes never overlap.
    """
    if len(boxes) == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    offset = boxes.abs().max() * 2 + 1
    return nms(boxes + (labels.to(boxes.dtype) * offset)[:, None], scores, iou_threshold)


def select_detections(boxes: torch.Tensor, probs: torch.Tensor, score_threshold: float,
                      iou_threshold: float, max_detections: int, max_candidates: int = 1000
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One image's detections from a dense detector's candidates.

    ``boxes`` ``N×4`` xyxy, ``probs`` ``N×C`` per-class probabilities. Each
    candidate keeps its best class; those scoring at least ``score_threshold``
    (at most the ``max_candidates`` best) go through :func:`batched_nms`; the
    ``max_detections`` best survivors are returned as ``(boxes, scores,
    labels)``, sorted by decreasing score.
    """
    scores, labels = probs.max(-1)
    keep = (scores >= score_threshold).nonzero().squeeze(1)
    keep = keep[scores[keep].argsort(descending=True)[:max_candidates]]
    kept = keep[batched_nms(boxes[keep], scores[keep], labels[keep], iou_threshold)][:max_detections]
    return boxes[kept], scores[kept], labels[kept]
