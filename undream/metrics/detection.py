"""Detection metrics: AP at one IoU threshold (0.5 by default), by pycocotools.

AP is COCO's: detections of a class over all frames ranked by score, matched
greedily to unmatched ground truth at IoU >= the threshold (a second
detection of an already matched object is a false positive), precision made
monotone and read at 101 recall points 0, 0.01, ..., 1, and averaged.
Computed by ``pycocotools.cocoeval.COCOeval`` with ``iouThrs = [threshold]``,
one area range (all) and no cap on detections that matters (``maxDets`` at
least the most detections in a frame).

Empty cases, made explicit:

- a class with ground truth but no detections has AP 0;
- a class without ground truth has no AP (None), whatever was detected:
  COCO leaves it out of the mean, and so does :func:`mean_average_precision`;
- no class with ground truth: mAP is None.
"""
from __future__ import annotations

import contextlib
import io
from typing import Any, Iterable, Sequence

import numpy as np

from undream.metrics.inputs import Detections, GroundTruth, MetricsError, frames_of
from undream.metrics.report import MetricsReport


def _xywh(boxes: np.ndarray) -> np.ndarray:
    out = boxes.copy()
    out[:, 2:] -= out[:, :2]
    return out


def _coco_inputs(dets: list[Detections], truths: list[GroundTruth], classes: list[int]
                 ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """COCO ground-truth dataset and result list; image id = frame + 1, category
    id = class + 1 and annotation ids from 1 (pycocotools treats 0 as unset)."""
    keep = set(classes)
    anns, results = [], []
    for i, (d, t) in enumerate(zip(dets, truths)):
        for box, lab in zip(_xywh(t.boxes), t.labels):
            if int(lab) in keep:
                anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": int(lab) + 1,
                             "bbox": box.tolist(), "area": float(box[2] * box[3]), "iscrowd": 0})
        for box, score, lab in zip(_xywh(d.boxes), d.scores, d.labels):
            if int(lab) in keep:
                results.append({"image_id": i + 1, "category_id": int(lab) + 1,
                                "bbox": box.tolist(), "score": float(score)})
    gt = {"images": [{"id": i + 1} for i in range(len(dets))],
          "categories": [{"id": c + 1} for c in classes], "annotations": anns}
    return gt, results


def per_class_ap(dets: Sequence[Any], truths: Sequence[Any], iou_threshold: float = 0.5,
                 classes: Iterable[int] | None = None) -> dict[int, float | None]:
    """AP at ``iou_threshold`` for each class (default: every class in the
    ground truth or the detections); None for a class without ground truth."""
    d, t = frames_of(dets, truths)
    if not 0.0 < iou_threshold <= 1.0:
        raise MetricsError(f"iou_threshold: must be in (0, 1], got {iou_threshold!r}")
    if classes is None:
        classes = {int(c) for f in t for c in f.labels} | {int(c) for f in d for c in f.labels}
    cls = sorted({int(c) for c in classes})
    has_gt = {c: any((f.labels == c).any() for f in t) for c in cls}
    gt, results = _coco_inputs(d, t, cls)
    if not results or not gt["annotations"]:
        return {c: (0.0 if has_gt[c] else None) for c in cls}
    precision = _coco_precision(gt, results, iou_threshold, max(len(f.scores) for f in d))
    out: dict[int, float | None] = {}
    for k, c in enumerate(cls):
        p = precision[0, :, k, 0, 0]
        out[c] = float(p[p > -1].mean()) if (p > -1).any() else None
    return out


def _coco_precision(gt: dict[str, Any], results: list[dict[str, Any]], iou_threshold: float,
                    max_dets: int) -> np.ndarray:
    """``COCOeval.eval['precision']`` (T×R×K×A×M); pycocotools' prints silenced."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(results)
        ev = COCOeval(coco_gt, coco_dt, iouType="bbox")
        ev.params.imgIds = [im["id"] for im in gt["images"]]
        ev.params.catIds = [c["id"] for c in gt["categories"]]
        ev.params.iouThrs = np.array([iou_threshold])
        ev.params.areaRng = [[0.0, 1e12]]
        ev.params.areaRngLbl = ["all"]
        ev.params.maxDets = [max(100, max_dets)]
        ev.evaluate()
        ev.accumulate()
    return ev.eval["precision"]


def average_precision(dets: Sequence[Any], truths: Sequence[Any], label: int,
                      iou_threshold: float = 0.5) -> float | None:
    """AP of class ``label`` over all frames (None if it has no ground truth)."""
    return per_class_ap(dets, truths, iou_threshold, classes=[label])[int(label)]


def mean_average_precision(dets: Sequence[Any], truths: Sequence[Any], iou_threshold: float = 0.5,
                           classes: Iterable[int] | None = None) -> float | None:
    """Mean AP over the classes that have ground truth (None if none has)."""
    aps = [v for v in per_class_ap(dets, truths, iou_threshold, classes).values() if v is not None]
    return float(np.mean(aps)) if aps else None


def best_match(dets: Any, truth: Any, label: int) -> tuple[float, float | None]:
    """Best IoU of a ``label`` detection with a ``label`` true box in one frame,
    and that detection's score (IoU by ``pycocotools.mask.iou``; 0 and None
    when there is no such pair)."""
    from pycocotools import mask
    d, t = Detections.of(dets), GroundTruth.of(truth)
    db, ds = d.boxes[d.labels == label], d.scores[d.labels == label]
    tb = t.boxes[t.labels == label]
    if not len(db) or not len(tb):
        return 0.0, None
    iou = np.asarray(mask.iou(_xywh(db).tolist(), _xywh(tb).tolist(), [0] * len(tb)))
    best = np.unravel_index(int(np.argmax(iou)), iou.shape)
    return float(iou[best]), float(ds[best[0]])


def is_detected(dets: Any, truth: Any, label: int, iou_threshold: float = 0.5) -> bool:
    """Whether some ``label`` detection overlaps a ``label`` true box at IoU >=
    ``iou_threshold`` (the detections as given: threshold scores first)."""
    return best_match(dets, truth, label)[0] >= iou_threshold


def detection_report(dets: Sequence[Any], truths: Sequence[Any], object_label: int,
                     iou_threshold: float = 0.5,
                     classes: Iterable[int] | None = None) -> MetricsReport:
    """AP of the object's class and mAP, aggregated and per frame.

    Per frame: ``detected`` (see :func:`is_detected`), ``best_iou``, ``score``,
    ``ap`` (the object's class in that frame alone; None without its ground
    truth) and ``n_detections``. Aggregate: ``ap`` (object class), ``map``,
    ``ap_per_class``, ``detection_rate`` (over frames where the object is in
    the ground truth) and counts.
    """
    d, t = frames_of(dets, truths)
    label = int(object_label)
    rows = []
    for i, (df, tf) in enumerate(zip(d, t)):
        iou, score = best_match(df, tf, label)
        rows.append({"frame": i, "detected": iou >= iou_threshold, "best_iou": iou, "score": score,
                     "ap": average_precision([df], [tf], label, iou_threshold),
                     "n_detections": int(len(df.scores))})
    aps = per_class_ap(d, t, iou_threshold, classes)
    defined = [v for v in aps.values() if v is not None]
    ap = aps[label] if label in aps else average_precision(d, t, label, iou_threshold)
    present = [r for r, tf in zip(rows, t) if (tf.labels == label).any()]
    agg = {"ap": ap, "map": float(np.mean(defined)) if defined else None,
           "ap_per_class": {str(c): v for c, v in sorted(aps.items())},
           "detection_rate": (sum(r["detected"] for r in present) / len(present)) if present else None,
           "n_frames": len(rows), "n_frames_with_object": len(present)}
    return MetricsReport("detection", "detection", rows, agg,
                         {"iou_threshold": iou_threshold, "object_label": label})
