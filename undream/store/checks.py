"""Checks of the values the store is given; errors name the field, the value and what is valid."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from undream.errors import StoreError
from undream.store.snapshots import dumps, finite_or_none

RECORD_FIELDS = ("loss_mean", "n_ok", "n_bad", "dropped_frames", "grad_norm", "step_seconds",
                 "per_frame", "terms")
MAX_SEED = 2**63 - 1


def integer(field: str, value: Any, minimum: int, maximum: int = 2**31 - 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not minimum <= value <= maximum:
        raise StoreError(f"{field}: must be an integer in [{minimum}, {maximum}], got {value!r}")
    return int(value)


def number(field: str, value: Any) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise StoreError(f"{field}: must be a number or None, got {value!r}")
    return finite_or_none(value)


def texture(field: str, array: Any) -> np.ndarray:
    """Check an H×W×3 float sRGB texture in [0, 1]."""
    arr = np.asarray(array)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise StoreError(f"{field}: must be an H×W×3 texture, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise StoreError(f"{field}: must be a float array of sRGB values in [0, 1], "
                         f"got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)) or arr.min() < 0.0 or arr.max() > 1.0:
        raise StoreError(f"{field}: values must be finite sRGB in [0, 1], "
                         f"got range [{np.nanmin(arr)}, {np.nanmax(arr)}]")
    return arr


def mapping(field: str, value: Any, what: str = "") -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise StoreError(f"{field}: must be a mapping{what}, got {type(value).__name__}")
    return value


def _frames(value: Any) -> list[int]:
    if not isinstance(value, (list, tuple)):
        raise StoreError(f"record.dropped_frames: must be a list of frame indexes, got {value!r}")
    return [integer("record.dropped_frames", f, 0) for f in value]


def record_values(record: Mapping[str, Any]) -> dict[str, Any]:
    """The columns of an iteration record (fields ``RECORD_FIELDS``)."""
    if not isinstance(record, Mapping):
        raise StoreError(f"record: must be a mapping of {', '.join(RECORD_FIELDS)}, got {record!r}")
    unknown = sorted(set(record) - set(RECORD_FIELDS))
    if unknown:
        raise StoreError(f"record: unknown field(s) {', '.join(map(str, unknown))}; "
                         f"valid fields are {', '.join(RECORD_FIELDS)}")
    return {
        "loss_mean": number("record.loss_mean", record.get("loss_mean")),
        "n_ok": integer("record.n_ok", record.get("n_ok", 0), 0),
        "n_bad": integer("record.n_bad", record.get("n_bad", 0), 0),
        "grad_norm": number("record.grad_norm", record.get("grad_norm")),
        "step_seconds": number("record.step_seconds", record.get("step_seconds")),
        "dropped_json": dumps("record.dropped_frames", _frames(record.get("dropped_frames", []))),
        "per_frame_json": dumps("record.per_frame", record.get("per_frame", [])),
        "terms_json": dumps("record.terms", _terms(record["terms"])) if record.get("terms") else None,
    }


def _terms(value: Any) -> dict[str, float | None]:
    """The objective's named terms of one step (``loss_victim``, ``loss_total``, ``reg_tv``, ...)."""
    terms = mapping("record.terms", value, " of term name → number")
    return {str(k): number(f"record.terms.{k}", v) for k, v in terms.items()}
