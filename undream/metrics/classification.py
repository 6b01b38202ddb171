"""Classification accuracy, per frame and over a sequence."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from undream.metrics.inputs import MetricsError, as_array
from undream.metrics.report import MetricsReport


def labels_of(preds: Sequence[Any], field: str = "predictions") -> np.ndarray:
    """Class ids from ints or from predictions with a ``.label`` (a victim's)."""
    return as_array([getattr(p, "label", p) for p in preds], field, np.int64).reshape(-1)


def true_labels_of(true_labels: int | Sequence[int], n: int) -> np.ndarray:
    """One true class id per frame (one int is broadcast to all ``n`` frames)."""
    if isinstance(true_labels, (int, np.integer)) and not isinstance(true_labels, bool):
        true_labels = [int(true_labels)] * n
    y = as_array(true_labels, "true_labels", np.int64).reshape(-1)
    if y.shape != (n,):
        raise MetricsError(f"true_labels: need one per frame ({n}), got {y.shape[0]}")
    return y


def correct(preds: Sequence[Any], true_labels: int | Sequence[int]) -> np.ndarray:
    """Per frame: was the predicted class the true one (bool array)."""
    p = labels_of(preds)
    return p == true_labels_of(true_labels, len(p))


def accuracy(preds: Sequence[Any], true_labels: int | Sequence[int]) -> float | None:
    """Fraction of frames classified correctly; None for no frames."""
    ok = correct(preds, true_labels)
    return float(ok.mean()) if ok.size else None


def classification_report(preds: Sequence[Any], true_labels: int | Sequence[int]) -> MetricsReport:
    """Accuracy per frame (``correct``) and aggregated (``accuracy``)."""
    p = labels_of(preds)
    y = true_labels_of(true_labels, len(p))
    ok = p == y
    rows = [{"frame": i, "pred": int(a), "true": int(b), "correct": bool(c)}
            for i, (a, b, c) in enumerate(zip(p, y, ok))]
    agg = {"accuracy": float(ok.mean()) if ok.size else None, "n_frames": int(ok.size),
           "n_correct": int(ok.sum())}
    return MetricsReport("classification", "accuracy", rows, agg)
