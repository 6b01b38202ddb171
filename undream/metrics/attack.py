"""Attack success rate, per frame and over a sequence.

A frame is *eligible* when the victim got it right without the attack (the
benign prediction was correct), and a *success* when it is eligible and the
attack fooled the victim:

- classification, untargeted: the adversarial prediction is not the true class;
- classification, targeted: the adversarial prediction is the target class;
- detection, untargeted (vanish): the object is no longer detected, i.e. no
  detection of its true class overlaps its true box at IoU >= the threshold;
- detection, targeted (mislabel): a detection of the target class overlaps the
  object's box at IoU >= the threshold and none of the true class does.

``success_rate`` is successes over eligible frames (the usual definition;
None when no frame is eligible); ``success_rate_all`` is successes over all
frames. Detections are taken as given: apply the score threshold first.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from undream.metrics.classification import labels_of, true_labels_of
from undream.metrics.detection import is_detected
from undream.metrics.inputs import GroundTruth, MetricsError, frames_of
from undream.metrics.report import MetricsReport


def attack_success(benign_correct: Sequence[bool], fooled: Sequence[bool]) -> np.ndarray:
    """Per frame: the benign prediction was correct and the attack fooled it."""
    b = np.asarray(benign_correct, dtype=bool).reshape(-1)
    f = np.asarray(fooled, dtype=bool).reshape(-1)
    if b.shape != f.shape:
        raise MetricsError(f"attack_success: {b.size} benign frames but {f.size} adversarial")
    return b & f


def _summary(benign_ok: np.ndarray, success: np.ndarray) -> dict[str, Any]:
    n, eligible, hits = int(success.size), int(benign_ok.sum()), int(success.sum())
    return {"success_rate": hits / eligible if eligible else None,
            "success_rate_all": hits / n if n else None,
            "n_frames": n, "n_eligible": eligible, "n_success": hits}


def classification_attack_report(benign: Sequence[Any], adversarial: Sequence[Any],
                                 true_labels: int | Sequence[int],
                                 target_label: int | None = None) -> MetricsReport:
    """Success per frame and rate; predictions are class ids or objects with ``.label``."""
    b, a = labels_of(benign, "benign"), labels_of(adversarial, "adversarial")
    if b.shape != a.shape:
        raise MetricsError(f"adversarial: {a.size} frames but {b.size} benign; need one each")
    y = true_labels_of(true_labels, len(b))
    ok = b == y
    fooled = a != y if target_label is None else a == int(target_label)
    success = attack_success(ok, fooled)
    rows = [{"frame": i, "true": int(y[i]), "benign": int(b[i]), "adversarial": int(a[i]),
             "benign_correct": bool(ok[i]), "success": bool(success[i])} for i in range(len(b))]
    return MetricsReport("classification", "attack_success", rows, _summary(ok, success),
                         {"target_label": target_label})


def detection_attack_report(benign: Sequence[Any], adversarial: Sequence[Any],
                            truths: Sequence[Any], object_label: int,
                            target_label: int | None = None,
                            iou_threshold: float = 0.5) -> MetricsReport:
    """Success per frame and rate for a detector (see the module docstring)."""
    bd, t = frames_of(benign, truths, "benign")
    ad, _ = frames_of(adversarial, truths, "adversarial")
    label = int(object_label)
    rows, ok, success = [], [], []
    for i, (bf, af, tf) in enumerate(zip(bd, ad, t)):
        benign_ok = is_detected(bf, tf, label, iou_threshold)
        still = is_detected(af, tf, label, iou_threshold)
        fooled = not still
        as_target = None
        if target_label is not None:
            obj = GroundTruth(tf.boxes[tf.labels == label],
                              np.full(int((tf.labels == label).sum()), int(target_label)))
            as_target = is_detected(af, obj, int(target_label), iou_threshold)
            fooled = fooled and as_target
        ok.append(benign_ok)
        success.append(benign_ok and fooled)
        rows.append({"frame": i, "benign_detected": benign_ok, "adversarial_detected": still,
                     "adversarial_as_target": as_target, "success": benign_ok and fooled})
    summary = _summary(np.asarray(ok, dtype=bool), np.asarray(success, dtype=bool))
    return MetricsReport("detection", "attack_success", rows, summary,
                         {"object_label": label, "target_label": target_label,
                          "iou_threshold": iou_threshold})
