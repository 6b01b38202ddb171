"""Metrics of victims and attacks over frame sequences, with JSON reports.

Classification accuracy; detection AP and mAP at IoU 0.5 (pycocotools'
COCOeval, not re-implemented); attack success rate. Each comes per frame and
aggregated, as a :class:`MetricsReport` that writes JSON. Inputs are plain
numpy/list data or a victim's predictions; this package imports no torch.
"""
from __future__ import annotations

from undream.metrics.attack import (
    attack_success,
    classification_attack_report,
    detection_attack_report,
)
from undream.metrics.classification import accuracy, classification_report, correct
from undream.metrics.detection import (
    average_precision,
    best_match,
    detection_report,
    is_detected,
    mean_average_precision,
    per_class_ap,
)
from undream.metrics.inputs import Detections, GroundTruth, MetricsError
from undream.metrics.report import MetricsReport

__all__ = [
    "Detections", "GroundTruth", "MetricsError", "MetricsReport",
    "accuracy", "attack_success", "average_precision", "best_match",
    "classification_attack_report", "classification_report", "correct",
    "detection_attack_report", "detection_report", "is_detected",
    "mean_average_precision", "per_class_ap",
]
