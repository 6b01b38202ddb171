"""Victims: the perception models under attack, behind one interface.

Images in are sRGB values in [0, 1], ``B×3×H×W`` float torch tensors. Every
victim's :meth:`~Victim.loss` is MAXIMISED by the attack (larger = more
successful). Load one with :func:`load_victim` (a Hugging Face hub id, a
``save_pretrained`` folder, an undream YOLO folder, a YOLOv8/YOLO11 ``*.pt``
where ultralytics is installed, or ``bundled:NAME``, e.g. ``bundled:classifier-v2``), or wrap any
``torch.nn.Module`` in :class:`Classifier`, :class:`Detector` (DETR-style set
prediction) or :class:`DenseDetector` (YOLO-style dense candidates).

The Hugging Face adapters (:class:`HFClassifier`, :class:`HFDetector`) are
imported on first use so that importing this package does not import
``transformers``.
"""
from __future__ import annotations

from typing import Any

from undream.victims.base import (
    TASKS,
    ClassPrediction,
    DetPrediction,
    Target,
    Victim,
    check_images,
)
from undream.victims.classifier import CLASSIFICATION_LOSSES, Classifier
from undream.victims.dense import DenseDetector, DenseOutput
from undream.victims.detector import DETECTION_LOSSES, DetectionOutput, Detector
from undream.victims.preprocess import PreprocessConfig, preprocess_images
from undream.victims.registry import (BUNDLED, BUNDLED_ALIASES, bundled_names, bundled_path,
                                      load_victim)

_LAZY = {"HFClassifier", "HFDetector", "load_hf_victim"}

__all__ = [
    "BUNDLED", "BUNDLED_ALIASES", "CLASSIFICATION_LOSSES", "DETECTION_LOSSES", "TASKS",
    "ClassPrediction", "Classifier", "DenseDetector", "DenseOutput", "DetPrediction",
    "DetectionOutput", "Detector",
    "PreprocessConfig", "Target", "Victim", "bundled_names", "bundled_path", "check_images",
    "load_victim", "preprocess_images", *sorted(_LAZY),
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from undream.victims import hf
        return getattr(hf, name)
    raise AttributeError(f"module 'undream.victims' has no attribute {name!r}")
