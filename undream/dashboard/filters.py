"""Jinja filters: durations, percentages, numbers and sparklines for the pages."""
from __future__ import annotations

import datetime as dt
import json
from typing import Any, Callable

from undream.charts import sparkline


def duration(seconds: float | None) -> str:
    """``3 h 05 min``, ``4 min 10 s``, ``12 s``, ``0.42 s``; an en dash for None."""
    if seconds is None:
        return "–"
    if seconds < 10:
        return f"{seconds:.2f} s"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min" if s % 60 == 0 else f"{s // 60} min {s % 60:02d} s"
    if s < 86400:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    return f"{s // 86400} d {s % 86400 // 3600} h"


def percent(value: float | None) -> str:
    """A fraction in [0, 1] as ``87.5 %``; an en dash for None."""
    return "–" if value is None else f"{100.0 * value:.1f} %"


def number(value: Any, digits: int = 4) -> str:
    """A number with ``digits`` significant digits; anything else as text; an en dash for None."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def clock(stamp: str | None) -> str:
    """An ISO time as ``YYYY-MM-DD HH:MM:SS UTC``."""
    if not stamp:
        return "–"
    return dt.datetime.fromisoformat(stamp).astimezone(dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def pretty(data: Any) -> str:
    return json.dumps(data, indent=2, sort_keys=True)


def short_id(run_id: str) -> str:
    return run_id[:8]


FILTERS: dict[str, Callable[..., Any]] = {
    "duration": duration, "percent": percent, "number": number, "clock": clock, "pretty": pretty,
    "short_id": short_id, "sparkline": sparkline,
}
