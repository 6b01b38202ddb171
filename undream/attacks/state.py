"""Attack state to plain JSON and back, exactly.

An attack's state is a flat ``dict[str, value]`` whose values are tensors,
numbers, booleans, strings, None or lists of those. Between iterations the farm
stores it: tensors may go to blobs and the rest to JSON, or everything to JSON
through :func:`state_to_dict`, which writes

- a tensor as ``{"tensor": dtype, "shape": [...], "data": [flat values]}``
  (float32 values survive the trip through Python floats bit for bit);
- a non-finite float as ``{"float": "inf" | "-inf" | "nan"}`` (strict JSON,
  e.g. PostgreSQL's, has no Infinity).

``state_from_dict(json.loads(json.dumps(state_to_dict(s))))`` equals ``s``.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import torch

from undream.errors import AttackError

_DTYPES = {str(d).removeprefix("torch."): d for d in
           (torch.float16, torch.float32, torch.float64, torch.bool,
            torch.uint8, torch.int32, torch.int64)}


def _encode(key: str, value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        name = str(value.dtype).removeprefix("torch.")
        if name not in _DTYPES:
            raise AttackError(f"state.{key}: tensor dtype {name} cannot be stored; "
                              f"valid dtypes are {', '.join(_DTYPES)}")
        return {"tensor": name, "shape": list(value.shape),
                "data": value.detach().cpu().reshape(-1).tolist()}
    if isinstance(value, float) and not math.isfinite(value):
        return {"float": repr(value)}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_encode(key, v) for v in value]
    raise AttackError(f"state.{key}: cannot store a {type(value).__name__}; "
                      "values must be tensors, numbers, booleans, strings, None or lists")


def _decode(key: str, value: Any) -> Any:
    if isinstance(value, Mapping):
        if "tensor" in value:
            dtype = _DTYPES.get(value["tensor"])
            if dtype is None:
                raise AttackError(f"state.{key}: unknown tensor dtype {value['tensor']!r}; "
                                  f"valid dtypes are {', '.join(_DTYPES)}")
            return torch.tensor(value["data"], dtype=dtype).reshape(value["shape"])
        if "float" in value:
            return float(value["float"])
        raise AttackError(f"state.{key}: a mapping must hold 'tensor' or 'float', "
                          f"got keys {sorted(value)}")
    if isinstance(value, list):
        return [_decode(key, v) for v in value]
    return value


def state_to_dict(state: Mapping[str, Any]) -> dict[str, Any]:
    """The state as plain JSON-able data (see the module docstring)."""
    return {str(k): _encode(str(k), v) for k, v in state.items()}


def state_from_dict(data: Mapping[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`state_to_dict`."""
    if not isinstance(data, Mapping):
        raise AttackError(f"state: must be a mapping, got {type(data).__name__}")
    return {str(k): _decode(str(k), v) for k, v in data.items()}
