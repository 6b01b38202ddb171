"""A metrics result: per-frame rows and an aggregate, with a JSON round trip."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from undream.metrics.inputs import MetricsError


def jsonable(value: Any) -> Any:
    """``value`` with numpy scalars and arrays as Python, tuples as lists, dict
    keys as strings, and NaN or infinities as None (JSON has no NaN)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True)
class MetricsReport:
    """Results of one metric over a sequence of frames.

    task: ``classification`` or ``detection``; metric: what was measured
    (``accuracy``, ``detection``, ``attack_success``); per_frame: one dict per
    frame, in frame order; aggregate: the totals; params: what they depend on
    (an IoU threshold, a target class). Undefined values (an AP without
    ground truth, a rate over zero frames) are None.
    """

    task: str
    metric: str
    per_frame: list[dict[str, Any]]
    aggregate: dict[str, Any]
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return jsonable({"task": self.task, "metric": self.metric, "params": self.params,
                         "aggregate": self.aggregate, "per_frame": self.per_frame})

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def save(self, path: str | Path) -> Path:
        """Write the report as JSON to ``path``; returns the path."""
        p = Path(path)
        p.write_text(self.to_json() + "\n", encoding="utf-8")
        return p

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "MetricsReport":
        try:
            return cls(task=d["task"], metric=d["metric"], per_frame=list(d["per_frame"]),
                       aggregate=dict(d["aggregate"]), params=dict(d.get("params", {})))
        except (KeyError, TypeError) as err:
            raise MetricsError(f"metrics report: missing or bad field {err}") from err

    @classmethod
    def load(cls, path: str | Path) -> "MetricsReport":
        try:
            return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, ValueError) as err:
            if isinstance(err, MetricsError):
                raise
            raise MetricsError(f"{path}: cannot read metrics report ({err})") from err
