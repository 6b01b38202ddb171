"""Training loss of undream's YOLO-style detector (:class:`undream.victims.yolo.YoloNet`).

Assignment is centre-based (FCOS's centre sampling): a candidate is a
POSITIVE of a true box when its cell centre lies inside the box and within
``radius`` strides of the box's centre on both axes; a candidate inside two
boxes goes to the smaller one; a box holding no cell centre (smaller than a
stride) gets the finest level's cell nearest to its centre. Every other
candidate is a negative.

Loss = ``cls_weight`` · BCE(class logits, one-hot of the assigned class at
positives, zeros elsewhere), summed over candidates and classes, divided by
the number of positives, + ``box_weight`` · mean over positives of (1 − GIoU)
of the predicted and the assigned true box.

Shapes: candidates ``B×N×(4 + C)`` as :meth:`YoloNet.forward` returns them
(xyxy pixels of the model input, logits); true boxes ``B×M×4`` xyxy in the
same pixels, labels ``B×M`` class ids, ``-1`` for padding (images with fewer
than M objects).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from undream.errors import VictimError
from undream.victims.losses import box_iou_giou
from undream.victims.yolo import STRIDES, YoloConfig, YoloNet, anchor_points

YOLO_ARCH: dict[str, object] = {"widths": (16, 24, 32, 48, 64), "depth": 1, "neck": 32, "head": 32}


@dataclass(frozen=True)
class YoloLossConfig:
    """Weights of the two terms and the centre-sampling radius (in strides)."""

    cls_weight: float = 1.0
    box_weight: float = 2.0
    radius: float = 2.5


def assign(boxes: torch.Tensor, labels: torch.Tensor, points: torch.Tensor, strides: torch.Tensor,
           radius: float = 2.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre-based assignment (see the module docstring).

    ``boxes`` ``B×M×4``, ``labels`` ``B×M`` (``-1`` padding), ``points`` ``N×2``,
    ``strides`` ``N``. Returns ``positive`` ``B×N`` (bool) and ``index`` ``B×N``,
    the true box (0..M-1) each candidate is assigned (meaningful at positives).
    """
    valid = labels >= 0  # B×M
    px, py = points[:, 0], points[:, 1]
    b = boxes[..., None, :]  # B×M×1×4
    inside = (px > b[..., 0]) & (px < b[..., 2]) & (py > b[..., 1]) & (py < b[..., 3])  # B×M×N
    cx, cy = (b[..., 0] + b[..., 2]) / 2, (b[..., 1] + b[..., 3]) / 2
    near = ((px - cx).abs() < radius * strides) & ((py - cy).abs() < radius * strides)
    match = inside & near & valid[..., None]
    empty = valid & ~match.any(-1)  # boxes with no cell centre: the nearest finest-level cell
    if bool(empty.any()):
        finest = strides == strides.min()
        dist = (px - cx) ** 2 + (py - cy) ** 2 + torch.where(finest, 0.0, float("inf"))
        nearest = F.one_hot(dist.argmin(-1), len(points)).bool()  # B×M×N
        match |= nearest & empty[..., None]
    area = ((boxes[..., 2] - boxes[..., 0]) * (boxes[..., 3] - boxes[..., 1]))[..., None]  # B×M×1
    cost = area.expand(match.shape).masked_fill(~match, float("inf"))
    best, index = cost.min(1)  # B×N: the smallest matching box
    return torch.isfinite(best), index


def yolo_loss(candidates: torch.Tensor, boxes: torch.Tensor, labels: torch.Tensor,
              size: tuple[int, int], config: YoloLossConfig = YoloLossConfig()
              ) -> tuple[torch.Tensor, dict[str, float]]:
    """The training loss (a scalar) and its terms, for candidates of an input of ``size`` (h, w)."""
    if boxes.ndim != 3 or boxes.shape[-1] != 4 or labels.shape != boxes.shape[:2]:
        raise VictimError(f"yolo_loss: true boxes must be B×M×4 and labels B×M, got "
                          f"{tuple(boxes.shape)} and {tuple(labels.shape)}")
    points, strides = anchor_points(*size, STRIDES, candidates.device)
    if candidates.shape[1] != len(points):
        raise VictimError(f"yolo_loss: {candidates.shape[1]} candidates for a {size[0]}×{size[1]} "
                          f"input, expected {len(points)}")
    pred_boxes, logits = candidates[..., :4], candidates[..., 4:]
    positive, index = assign(boxes, labels, points, strides, config.radius)
    true_boxes = boxes.gather(1, index[..., None].expand(-1, -1, 4))  # B×N×4
    true_labels = labels.gather(1, index)
    target = F.one_hot(true_labels.clamp(min=0), logits.shape[-1]).to(logits.dtype)
    target = target * positive[..., None]
    n_pos = positive.sum().clamp(min=1).to(logits.dtype)
    cls = F.binary_cross_entropy_with_logits(logits, target, reduction="sum") / n_pos
    _, giou = box_iou_giou(pred_boxes[positive], true_boxes[positive])
    box = (1 - giou).sum() / n_pos
    loss = config.cls_weight * cls + config.box_weight * box
    return loss, {"cls": float(cls.detach()), "box": float(box.detach()), "positives": float(positive.sum())}


def build_yolo(labels: tuple[str, ...], input_size: int, **arch: object) -> YoloNet:
    """A fresh :class:`YoloNet` over ``labels`` (random weights; ``arch`` overrides
    :data:`YOLO_ARCH`)."""
    return YoloNet(YoloConfig(labels=tuple(labels), input_size=input_size,
                              **{**YOLO_ARCH, **arch}))  # type: ignore[arg-type]


SQUARE_COLOURS = ((1.0, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.2, 1.0))  # classes 0, 1, 2: red, green, blue


def synthetic_squares(n: int, size: int, gen: torch.Generator, max_objects: int = 2
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A synthetic detection set for tests and smoke runs (nothing rendered).

    ``n`` sRGB [0, 1] images ``n×3×size×size`` of uniform noise in [0.25, 0.75]
    holding 1 to ``max_objects`` solid squares (side ``size/5`` to ``size/2``,
    later ones painted over earlier ones), each red, green or blue (classes 0,
    1, 2: :data:`SQUARE_COLOURS`). Returns the images, their boxes ``n×M×4``
    (xyxy pixels) and labels ``n×M`` (``-1`` for padding).
    """
    images = torch.rand(n, 3, size, size, generator=gen) * 0.5 + 0.25
    boxes = torch.zeros(n, max_objects, 4)
    labels = torch.full((n, max_objects), -1, dtype=torch.long)
    colours = torch.tensor(SQUARE_COLOURS)
    for i in range(n):
        for j in range(int(torch.randint(1, max_objects + 1, (1,), generator=gen))):
            side = int(torch.randint(size // 5, size // 2 + 1, (1,), generator=gen))
            x0, y0 = (int(v) for v in torch.randint(0, size - side + 1, (2,), generator=gen))
            c = int(torch.randint(0, len(SQUARE_COLOURS), (1,), generator=gen))
            images[i, :, y0:y0 + side, x0:x0 + side] = colours[c][:, None, None]
            boxes[i, j] = torch.tensor([x0, y0, x0 + side, y0 + side], dtype=torch.float32)
            labels[i, j] = c
    return images, boxes, labels
