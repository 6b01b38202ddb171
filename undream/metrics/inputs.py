"""Per-frame inputs of the metrics: detections and ground truth, as numpy.

Boxes are ``(x0, y0, x1, y1)`` in pixels of the frame. Anything with
``boxes``/``scores``/``labels`` (attributes or dict keys; numpy arrays, lists
or torch tensors) converts, so a victim's ``DetPrediction`` can be passed as
is. This module imports no torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from undream.errors import MetricsError


def _get(obj: Any, key: str) -> Any:
    if isinstance(obj, Mapping):
        if key not in obj:
            raise MetricsError(f"{key}: missing from {sorted(obj)}")
        return obj[key]
    if not hasattr(obj, key):
        raise MetricsError(f"{key}: missing from {type(obj).__name__}")
    return getattr(obj, key)


def as_array(value: Any, field: str, dtype: Any = np.float64) -> np.ndarray:
    """``value`` (list, numpy or torch) as a numpy array; finite numbers only."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MetricsError(f"{field}: must be numbers, got {value!r}") from err
    if not np.isfinite(arr).all():
        raise MetricsError(f"{field}: must be finite, got {arr.tolist()}")
    if dtype is np.int64:
        if (arr != np.round(arr)).any() or (arr < 0).any():
            raise MetricsError(f"{field}: must be class ids (ints >= 0), got {arr.tolist()}")
        return arr.astype(np.int64)
    return arr


def _boxes(value: Any, field: str) -> np.ndarray:
    arr = as_array(value, field)
    if arr.size == 0:
        return arr.reshape(0, 4)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise MetricsError(f"{field}: must be N×4 boxes (x0, y0, x1, y1), got shape {arr.shape}")
    if ((arr[:, 2] < arr[:, 0]) | (arr[:, 3] < arr[:, 1])).any():
        raise MetricsError(f"{field}: boxes must have x1 >= x0 and y1 >= y0, got {arr.tolist()}")
    return arr


def _same_length(field: str, arr: np.ndarray, n: int) -> np.ndarray:
    arr = arr.reshape(-1)
    if arr.shape != (n,):
        raise MetricsError(f"{field}: must have one entry per box ({n}), got {arr.shape[0]}")
    return arr


@dataclass(frozen=True)
class Detections:
    """One frame's detections: ``boxes`` N×4 xyxy pixels, ``scores`` N, ``labels`` N."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray

    def __post_init__(self) -> None:
        boxes = _boxes(self.boxes, "detections.boxes")
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", _same_length(
            "detections.scores", as_array(self.scores, "detections.scores"), len(boxes)))
        object.__setattr__(self, "labels", _same_length(
            "detections.labels", as_array(self.labels, "detections.labels", np.int64), len(boxes)))

    @classmethod
    def empty(cls) -> "Detections":
        return cls(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))

    @classmethod
    def of(cls, obj: Any) -> "Detections":
        """From anything with boxes, scores and labels (see the module docstring)."""
        if isinstance(obj, Detections):
            return obj
        return cls(_get(obj, "boxes"), _get(obj, "scores"), _get(obj, "labels"))


@dataclass(frozen=True)
class GroundTruth:
    """One frame's true objects: ``boxes`` M×4 xyxy pixels, ``labels`` M."""

    boxes: np.ndarray
    labels: np.ndarray

    def __post_init__(self) -> None:
        boxes = _boxes(self.boxes, "truth.boxes")
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "labels", _same_length(
            "truth.labels", as_array(self.labels, "truth.labels", np.int64), len(boxes)))

    @classmethod
    def single(cls, box: Sequence[float], label: int) -> "GroundTruth":
        """One object: ``box`` xyxy pixels, class ``label``."""
        return cls(np.asarray([box], dtype=np.float64), np.asarray([label]))

    @classmethod
    def of(cls, obj: Any) -> "GroundTruth":
        if isinstance(obj, GroundTruth):
            return obj
        return cls(_get(obj, "boxes"), _get(obj, "labels"))


def frames_of(dets: Sequence[Any], truths: Sequence[Any], what: str = "detections"
              ) -> tuple[list[Detections], list[GroundTruth]]:
    """Convert and check that there is one of each per frame."""
    d = [Detections.of(x) for x in dets]
    t = [GroundTruth.of(x) for x in truths]
    if len(d) != len(t):
        raise MetricsError(f"{what}: {len(d)} frames but ground truth for {len(t)}; "
                           f"need one per frame")
    return d, t
