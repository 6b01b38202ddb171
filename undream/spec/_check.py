"""Small validators shared by the spec dataclasses.

Each raises :class:`SpecError` whose message names the field and the value.
Paths compose: a container catches a child's error and prefixes its own
location, so a message reads ``frames[3].camera.fov_deg: must be ...``.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from typing import Any, Iterator, Mapping

from undream.errors import SpecError


def fail(field: str, value: Any, expected: str) -> SpecError:
    return SpecError(f"{field}: {expected}, got {value!r}")


@contextmanager
def at(prefix: str, catch: tuple[type[Exception], ...] = (SpecError,),
       raise_as: type[Exception] = SpecError) -> Iterator[None]:
    """Prefix the field path of any ``catch`` error raised inside the block (re-raised as ``raise_as``)."""
    try:
        yield
    except catch as err:
        msg = str(err)
        sep = "" if msg.startswith("[") else "."
        raise raise_as(f"{prefix}{sep}{msg}") from None


def finite(field: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(field, value, "must be a number")
    if not math.isfinite(value):
        raise fail(field, value, "must be finite")
    return float(value)


def positive(field: str, value: Any) -> float:
    v = finite(field, value)
    if v <= 0:
        raise fail(field, value, "must be > 0")
    return v


def integer(field: str, value: Any, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise fail(field, value, "must be an integer")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise fail(field, value, f"must be an integer in [{lo}, {hi}]")
    return value


def vector(field: str, value: Any, n: int) -> tuple[float, ...]:
    _sized(field, value, n, "numbers")
    return tuple(finite(f"{field}[{i}]", v) for i, v in enumerate(value))


WORLD_LIMIT_M = 1e6  # scenes live within a thousand kilometres of the origin


def point(field: str, value: Any) -> tuple[float, float, float]:
    """A position in metres, within ``WORLD_LIMIT_M`` of the origin on every axis."""
    v = vector(field, value, 3)
    for i, x in enumerate(v):
        if abs(x) > WORLD_LIMIT_M:
            raise fail(f"{field}[{i}]", x, f"must lie within ±{WORLD_LIMIT_M:g} m of the origin")
    return v  # type: ignore[return-value]


def length(field: str, value: Any, allow_zero: bool = False, signed: bool = False) -> float:
    """A distance in metres: > 0 (or ≥ 0, or any sign) and at most ``WORLD_LIMIT_M`` in size."""
    v = finite(field, value)
    if (v < 0 and not signed) or (v == 0 and not allow_zero and not signed):
        raise fail(field, value, "must be >= 0" if allow_zero else "must be > 0")
    if abs(v) > WORLD_LIMIT_M:
        raise fail(field, value, f"must be at most {WORLD_LIMIT_M:g} m")
    return v


def _sized(field: str, value: Any, n: int, what: str) -> None:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != n:
        raise fail(field, value, f"must be a list of {n} {what}")


def ints(field: str, value: Any, n: int, lo: int, hi: int) -> tuple[int, ...]:
    _sized(field, value, n, "integers")
    return tuple(integer(f"{field}[{i}]", v, lo, hi) for i, v in enumerate(value))


def color(field: str, value: Any) -> tuple[float, float, float]:
    rgb = vector(field, value, 3)
    if any(c < 0 or c > 1 for c in rgb):
        raise fail(field, value, "must be an sRGB colour with components in [0, 1]")
    return rgb  # type: ignore[return-value]


def choice(field: str, value: Any, options: tuple[str, ...]) -> str:
    if value not in options:
        raise fail(field, value, f"must be one of {', '.join(options)}")
    return value


NAME_MAX = 100  # characters of a name (a run's, a sequence's): it names folders and store rows


def name(field: str, value: Any) -> str:
    if not isinstance(value, str) or not value or not value.replace("_", "a").replace("-", "a").isalnum() \
            or len(value) > NAME_MAX:
        raise fail(field, value if not isinstance(value, str) or len(value) <= NAME_MAX else f"{value[:20]}…",
                   f"must be a non-empty name of at most {NAME_MAX} letters, digits, '_' or '-'")
    return value


def mapping(field: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise fail(field, value, "must be a mapping")
    return value


def require(d: Mapping[str, Any], key: str) -> Any:
    if key not in d:
        raise SpecError(f"{key}: is required")
    return d[key]


def no_extra(d: Mapping[str, Any], allowed: set[str]) -> None:
    extra = sorted(set(d) - allowed)
    if extra:
        raise SpecError(f"{extra[0]}: unknown field (valid: {', '.join(sorted(allowed))})")
