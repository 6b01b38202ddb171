"""Attack losses on model outputs, as plain functions.

Sign convention: every loss here is a quantity the ATTACK MAXIMISES. A larger
value means a more successful attack (the true class is less likely, the
target class more likely, the object's boxes further off). Gradient ascent on
the image or texture is the attack; nothing here needs negating.

Each loss computes one value per image; ``reduction="mean"`` (the default)
returns their mean over the batch, a scalar, and ``reduction="none"`` the
``B`` values themselves.

Classification losses take logits ``B×C``. Detection losses take the outputs
of a DETR-style detector, already turned into

- ``log_probs``: ``B×Q×C`` log of each query's per-class score (softmax over
  C + 1 classes with the last, "no object", dropped, for DETR; log-sigmoid for
  sigmoid-scored models such as Deformable DETR): see :func:`class_log_probs`;
- ``boxes``: ``B×Q×4`` predicted boxes, xyxy, normalised to [0, 1] by the
  image width and height: see :func:`cxcywh_to_xyxy`;
- ``weights``: ``B×Q`` non-negative, summing to 1 per image, saying which
  queries are "the object": see :func:`match_weights`.

Dense (one-stage, YOLO-style) detectors use the same three losses on their
candidates BEFORE non-maximum suppression (NMS picks boxes and has no useful
gradient), with "queries" = candidates and log-sigmoid scores; only the
weights differ: :func:`dense_weights`.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from undream.errors import VictimError

ACTIVATIONS = ("softmax", "sigmoid")
REDUCTIONS = ("mean", "none")


def _labels(y: torch.Tensor | int, batch: int, classes: int, device: torch.device,
            what: str = "label") -> torch.Tensor:
    """Class ids as a ``B`` long tensor, checked against ``classes``."""
    t = torch.as_tensor(y, device=device).long().reshape(-1)
    if t.numel() == 1:
        t = t.expand(batch)
    if t.shape != (batch,):
        raise VictimError(f"{what}: must be one class id or {batch} (one per image), "
                          f"got shape {tuple(t.shape)}")
    if bool(((t < 0) | (t >= classes)).any()):
        raise VictimError(f"{what}: class ids must be in [0, {classes - 1}], got {t.tolist()}")
    return t


def _reduce(values: torch.Tensor, reduction: str, what: str) -> torch.Tensor:
    """The ``B`` per-image ``values`` as asked: their mean (``mean``) or as they are (``none``)."""
    if reduction == "mean":
        return values.mean()
    if reduction == "none":
        return values
    raise VictimError(f"{what}.reduction: must be one of {', '.join(REDUCTIONS)}, got {reduction!r}")


# --------------------------------------------------------------------------- classification

def ce_untargeted(logits: torch.Tensor, y: torch.Tensor | int, *,
                  reduction: str = "mean") -> torch.Tensor:
    """Cross-entropy of the true class ``y``: maximise to move away from it."""
    yt = _labels(y, logits.shape[0], logits.shape[1], logits.device)
    return _reduce(F.cross_entropy(logits, yt, reduction="none"), reduction, "ce_untargeted")


def ce_targeted(logits: torch.Tensor, t: torch.Tensor | int, *,
                reduction: str = "mean") -> torch.Tensor:
    """Negative cross-entropy of the target class ``t``: maximise to reach it."""
    tt = _labels(t, logits.shape[0], logits.shape[1], logits.device, "target_label")
    return _reduce(-F.cross_entropy(logits, tt, reduction="none"), reduction, "ce_targeted")


def dlr(logits: torch.Tensor, y: torch.Tensor | int, *, reduction: str = "mean") -> torch.Tensor:
    """Difference of Logits Ratio (Croce & Hein, ICML 2020, eq. 5).

    ``DLR = -(z_y - max_{i != y} z_i) / (z_pi1 - z_pi3 + 1e-12)`` with ``z``
    sorted decreasingly as ``z_pi1 >= z_pi2 >= ...``. It is invariant to shifts
    and rescaling of the logits; it is > 0 exactly when the image is
    misclassified. Needs at least 3 classes.
    """
    if logits.shape[1] < 3:
        raise VictimError(f"dlr: needs at least 3 classes, the model has {logits.shape[1]}")
    yt = _labels(y, logits.shape[0], logits.shape[1], logits.device)
    z_sorted = logits.sort(dim=1, descending=True).values
    z_y = logits.gather(1, yt[:, None]).squeeze(1)
    z_other = _runner_up(logits, yt)
    ratio = (z_y - z_other) / (z_sorted[:, 0] - z_sorted[:, 2] + 1e-12)
    return _reduce(-ratio, reduction, "dlr")


MARGIN_KAPPA = 5.0  # :func:`margin`'s clip, in logits


def margin(logits: torch.Tensor, y: torch.Tensor | int, *, kappa: float = MARGIN_KAPPA,
           reduction: str = "mean") -> torch.Tensor:
    """Carlini & Wagner's margin (S&P 2017, f6 with confidence ``kappa``), untargeted:
    ``min(max_{i != y} z_i - z_y, kappa)``.

    > 0 exactly when the image is misclassified; clipped at ``kappa``, so a frame already wrong by
    that margin gives no gradient and a step over many frames goes to those still right (cross-entropy
    does the opposite: its gradient fades on frames the model is sure of and stays on frames it
    already gets wrong).
    """
    yt = _labels(y, logits.shape[0], logits.shape[1], logits.device)
    z_y = logits.gather(1, yt[:, None]).squeeze(1)
    return _reduce((_runner_up(logits, yt) - z_y).clamp(max=kappa), reduction, "margin")


def _runner_up(logits: torch.Tensor, yt: torch.Tensor) -> torch.Tensor:
    """``B``: each image's largest logit of a class other than its ``yt``."""
    return logits.masked_fill(F.one_hot(yt, logits.shape[1]).bool(), float("-inf")).max(dim=1).values


# --------------------------------------------------------------------------- detection helpers

def class_log_probs(logits: torch.Tensor, activation: str) -> torch.Tensor:
    """``B×Q×C`` log class scores from a detector's classification logits.

    ``softmax``: ``logits`` is ``B×Q×(C+1)``, the last class "no object" (DETR,
    YOLOS); the result drops it. ``sigmoid``: ``logits`` is ``B×Q×C``, one
    independent score per class (Deformable/Conditional DETR, RT-DETR).
    """
    if activation == "softmax":
        return logits.log_softmax(dim=-1)[..., :-1]
    if activation == "sigmoid":
        return F.logsigmoid(logits)
    raise VictimError(f"activation: must be one of {', '.join(ACTIVATIONS)}, got {activation!r}")


def _query_log_prob(log_probs: torch.Tensor, labels: torch.Tensor | int,
                    what: str = "label") -> torch.Tensor:
    """``B×Q``: each query's log score of its image's class ``labels[b]``."""
    batch, queries, classes = log_probs.shape
    y = _labels(labels, batch, classes, log_probs.device, what)
    return log_probs.gather(2, y[:, None, None].expand(-1, queries, 1)).squeeze(2)


def cxcywh_to_xyxy(boxes: torch.Tensor) -> torch.Tensor:
    """``(cx, cy, w, h)`` → ``(x0, y0, x1, y1)`` on the last axis; same units."""
    cx, cy, w, h = boxes.unbind(-1)
    return torch.stack((cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), dim=-1)


def box_iou_giou(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """IoU and generalised IoU of xyxy boxes ``a`` and ``b`` (broadcast ``...×4``)."""
    area_a = (a[..., 2] - a[..., 0]).clamp(min=0) * (a[..., 3] - a[..., 1]).clamp(min=0)
    area_b = (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)
    lt = torch.maximum(a[..., :2], b[..., :2])
    rb = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    union = area_a + area_b - inter
    iou = inter / union.clamp(min=1e-12)
    hull_wh = torch.maximum(a[..., 2:], b[..., 2:]) - torch.minimum(a[..., :2], b[..., :2])
    hull = hull_wh.clamp(min=0).prod(-1)
    giou = iou - (hull - union) / hull.clamp(min=1e-12)
    return iou, giou


def match_weights(log_probs: torch.Tensor, boxes: torch.Tensor, labels: torch.Tensor | int,
                  true_boxes: torch.Tensor | None = None, min_iou: float = 0.1) -> torch.Tensor:
    """Which queries are "the object": ``B×Q`` weights, >= 0, summing to 1 per image.

    With a true box (``true_boxes`` ``B×4``, normalised xyxy; a row of NaN means
    "no box for this image"), a query's weight is its IoU with the box, for
    queries with IoU >= ``min_iou``. Without a box, or where no query overlaps
    it that much, the weight is the query's probability of the true class:
    "wherever the detector finds it". The weights are detached: they select
    queries and carry no gradient.
    """
    with torch.no_grad():
        by_prob = _by_true_class(log_probs, labels)
        if true_boxes is None:
            return by_prob
        iou, _ = box_iou_giou(boxes, true_boxes[:, None, :])
        iou = torch.nan_to_num(iou, nan=0.0)
        iou = torch.where(iou >= min_iou, iou, torch.zeros_like(iou))
        total = iou.sum(1, keepdim=True)
        by_iou = iou / total.clamp(min=1e-12)
        return torch.where(total > 0, by_iou, by_prob)


def _by_true_class(log_probs: torch.Tensor, labels: torch.Tensor | int) -> torch.Tensor:
    """``B×Q`` weights ∝ each candidate's probability of the true class, summing to 1 per image:
    "wherever the detector finds it", both weightings' fallback."""
    p_true = _query_log_prob(log_probs, labels).exp()
    return p_true / p_true.sum(1, keepdim=True).clamp(min=1e-12)


def dense_weights(log_probs: torch.Tensor, boxes: torch.Tensor, labels: torch.Tensor | int,
                  true_boxes: torch.Tensor | None = None, points: torch.Tensor | None = None,
                  min_iou: float = 0.3) -> torch.Tensor:
    """Which candidates of a dense detector are "the object": ``B×N`` weights, >= 0,
    summing to 1 per image.

    A candidate is ON the object when its box overlaps the true box at IoU >=
    ``min_iou``, or when its cell centre (``points`` ``N×2``, normalised xy;
    None: this criterion is not used) lies inside the true box. On-object
    candidates are weighted by their score, their best class's probability (what
    NMS ranks them by), so that the candidates that become detections count
    most. Without a true box (``true_boxes`` None or a NaN row), or where no
    candidate is on the object, every candidate is weighted by its probability
    of the true class, as :func:`match_weights` does. Detached.
    """
    with torch.no_grad():
        by_prob = _by_true_class(log_probs, labels)
        if true_boxes is None:
            return by_prob
        iou, _ = box_iou_giou(boxes, true_boxes[:, None, :])
        on = torch.nan_to_num(iou, nan=0.0) >= min_iou
        if points is not None:
            tb = true_boxes[:, None, :]
            on |= ((points[None, :, 0] >= tb[..., 0]) & (points[None, :, 0] <= tb[..., 2])
                   & (points[None, :, 1] >= tb[..., 1]) & (points[None, :, 1] <= tb[..., 3]))
        score = log_probs.max(-1).values.exp() * on
        total = score.sum(1, keepdim=True)
        return torch.where(total > 0, score / total.clamp(min=1e-30), by_prob)


# --------------------------------------------------------------------------- detection losses

def det_vanish(log_probs: torch.Tensor, labels: torch.Tensor | int, weights: torch.Tensor,
               reduce: str = "mean", *, reduction: str = "mean") -> torch.Tensor:
    """Suppress the true class: ``-sum_q w_q p_q(y)`` (``reduce="mean"``).

    ``reduce="max"``: ``-max_q p_q(y)`` over the queries with ``w_q > 0`` (the
    strongest detection of the object only). Maximising drives the object's
    true-class score down wherever the detector finds it. In [-1, 0].
    ``reduce`` combines the queries of one image; ``reduction`` the images.
    """
    p = _query_log_prob(log_probs, labels).exp()
    if reduce == "mean":
        return _reduce(-(weights * p).sum(1), reduction, "det_vanish")
    if reduce == "max":
        return _reduce(-p.masked_fill(weights <= 0, 0.0).max(1).values, reduction, "det_vanish")
    raise VictimError(f"det_vanish.reduce: must be 'mean' or 'max', got {reduce!r}")


def det_mislabel(log_probs: torch.Tensor, target_labels: torch.Tensor | int,
                 weights: torch.Tensor, *, reduction: str = "mean") -> torch.Tensor:
    """Push the object's queries to the target class: ``sum_q w_q log p_q(t)``. <= 0."""
    lp = _query_log_prob(log_probs, target_labels, "target_label")
    return _reduce((weights * lp).sum(1), reduction, "det_mislabel")


def det_box(boxes: torch.Tensor, true_boxes: torch.Tensor, weights: torch.Tensor, *,
            reduction: str = "mean") -> torch.Tensor:
    """Move the object's boxes off it: ``sum_q w_q (L1(b_q, b) + 1 - GIoU(b_q, b))``.

    ``boxes`` ``B×Q×4`` and ``true_boxes`` ``B×4`` normalised xyxy; L1 is the
    mean over the four coordinates. The reverse of DETR's box-matching cost:
    0 when the matched boxes sit exactly on the object, growing as they leave.
    """
    l1 = (boxes - true_boxes[:, None, :]).abs().mean(-1)
    _, giou = box_iou_giou(boxes, true_boxes[:, None, :])
    return _reduce((weights * (l1 + 1.0 - giou)).sum(1), reduction, "det_box")
