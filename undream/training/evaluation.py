"""Held-out numbers of a victim on a dataset: overall and per group of images.

Groups: the weather, the background, and the test bands of the camera
parameters of the data's distribution (:data:`~undream.training.dataset.CAMERA_BANDS`:
camera height and ground distance for ``v2``, elevation and object size in
the frame for ``v1``), each band named by its interval (``[0.5, 0.8)``).
"""
from __future__ import annotations

from typing import Any, Callable, Iterator

import numpy as np
import torch

from undream.metrics import classification_report, is_detected, per_class_ap
from undream.training.bands import band_index, band_label
from undream.training.dataset import CAMERA_BANDS, CLASSES, Dataset, banded_values, bands_of, distribution_of

GROUPS = ("weather", "background")  # then the distribution's camera bands


def group_keys(record: dict[str, Any]) -> dict[str, tuple[float, str]]:
    """An image's group in each grouping: ``{grouping: (sort key, name)}``."""
    params = record["params"]
    env = params["environment"]
    dist = distribution_of(params)
    bands, values = bands_of(dist), banded_values(params)
    out = {"weather": (0.0, env["weather"]), "background": (0.0, env["background"])}
    for name in CAMERA_BANDS[dist]:
        out[name] = (float(band_index(bands, name, values[name])), band_label(bands, name, values[name]))
    return out


def _grouped(records: list[dict[str, Any]]) -> dict[str, dict[str, list[int]]]:
    """``{grouping: {group name: image indices}}``, groups sorted by band (or name)."""
    raw: dict[str, dict[tuple[float, str], list[int]]] = {}
    for i, rec in enumerate(records):
        for grouping, key in group_keys(rec).items():
            raw.setdefault(grouping, {}).setdefault(key, []).append(i)
    return {g: {name: idx for (_, name), idx in sorted(groups.items())} for g, groups in raw.items()}


def per_group(records: list[dict[str, Any]], score: Callable[[list[int]], float],
              measure: str) -> dict[str, dict[str, dict[str, Any]]]:
    """``{grouping: {group: {"n": images, measure: score(indices)}}}`` over :func:`group_keys`."""
    return {g: {name: {"n": len(idx), measure: score(idx)} for name, idx in groups.items()}
            for g, groups in _grouped(records).items()}


def _by(records: list[dict[str, Any]], ok: np.ndarray, key: Callable[[dict[str, Any]], str]
        ) -> dict[str, float]:
    groups: dict[str, list[bool]] = {}
    for rec, good in zip(records, ok):
        groups.setdefault(key(rec), []).append(bool(good))
    return {k: float(np.mean(v)) for k, v in sorted(groups.items())}


def _batches(ds: Dataset, size: int) -> Iterator[torch.Tensor]:
    for k in range(0, len(ds), size):
        yield torch.from_numpy(ds.images[k:k + size]).permute(0, 3, 1, 2).float() / 255.0


def _mean(aps: dict[int, float | None]) -> float:
    vals = [v for v in aps.values() if v is not None]
    return float(np.mean(vals)) if vals else float("nan")


def evaluate(victim: Any, ds: Dataset, batch: int = 100) -> dict[str, Any]:
    """Held-out numbers of a victim on a dataset.

    Classifier: ``accuracy`` (and per class, per weather, and ``per_group``:
    see :func:`per_group`). Detector: ``ap50`` = mean over classes of COCO AP
    at IoU 0.5 (pycocotools, every query's best class and score kept, as COCO
    scores DETR; also ``per_group``), ``ap50_thr05`` (only detections scoring
    >= 0.5) and ``top1_correct`` (the best-scoring detection has the right
    class and IoU >= 0.5).
    """
    weather = lambda r: r["params"]["environment"]["weather"]  # noqa: E731
    name = lambda r: r["name"]  # noqa: E731
    out: dict[str, Any] = {"n_images": len(ds), "victim": getattr(victim, "name", "?")}
    if victim.task == "classification":
        preds = []
        for x in _batches(ds, batch):
            preds += victim.predict(x)
        rep = classification_report(preds, ds.labels.tolist())
        ok = np.array([r["correct"] for r in rep.per_frame])
        out.update(accuracy=rep.aggregate["accuracy"], n_correct=rep.aggregate["n_correct"],
                   per_class=_by(ds.records, ok, name), per_weather=_by(ds.records, ok, weather),
                   per_group=per_group(ds.records, lambda idx: float(ok[idx].mean()), "accuracy"))
        return out
    preds = []
    for x in _batches(ds, batch):
        preds += victim.predict(x, threshold=0.0)
    truths = [{"boxes": [b.tolist()], "labels": [int(y)]} for b, y in zip(ds.boxes, ds.labels)]
    classes = list(range(len(CLASSES)))
    aps = per_class_ap(preds, truths, 0.5, classes)
    kept = [{"boxes": p.boxes[p.scores >= 0.5], "scores": p.scores[p.scores >= 0.5],
             "labels": p.labels[p.scores >= 0.5]} for p in preds]
    aps_thr = per_class_ap(kept, truths, 0.5, classes)
    top1 = np.array([is_detected({"boxes": p.boxes[:1], "scores": p.scores[:1], "labels": p.labels[:1]},
                                 t, int(y)) for p, t, y in zip(preds, truths, ds.labels)])

    def ap50_of(idx: list[int]) -> float:
        return _mean(per_class_ap([preds[i] for i in idx], [truths[i] for i in idx], 0.5, classes))

    out.update(ap50=_mean(aps), ap50_per_class={CLASSES[c]: v for c, v in aps.items()},
               ap50_thr05=_mean(aps_thr), top1_correct=float(top1.mean()),
               top1_per_weather=_by(ds.records, top1, weather), per_group=per_group(ds.records, ap50_of, "ap50"))
    return out
