"""The wire format between the ``blender`` backend and its render server (both sides import it).

One message is a fixed 8-byte prefix (two little-endian uint32: the JSON
header's length and the payload's length), the UTF-8 JSON header, then the
raw payload bytes (a C-contiguous float32 array whose shape the header
names under ``shape``). Standard library and numpy only: the server runs in
Blender's own environment (numpy < 2), the client in undream's (numpy 2).
"""
from __future__ import annotations

import json
import struct
from typing import Any, BinaryIO

import numpy as np

_PREFIX = struct.Struct("<II")
MAX_HEADER = 1 << 20  # bytes; a longer header means the stream is out of step


class ProtocolError(RuntimeError):
    """The other side closed the stream or sent something that is not a message."""


def write_message(stream: BinaryIO, header: dict[str, Any], array: np.ndarray | None = None) -> None:
    """Send ``header`` (JSON-able) and, if given, ``array`` as float32 (its shape goes in the header)."""
    payload = b""
    if array is not None:
        arr = np.ascontiguousarray(array, dtype=np.float32)
        header = {**header, "shape": list(arr.shape)}
        payload = arr.tobytes()
    head = json.dumps(header).encode("utf-8")
    stream.write(_PREFIX.pack(len(head), len(payload)) + head + payload)
    stream.flush()


def _read_exact(stream: BinaryIO, n: int) -> bytes:
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise ProtocolError(f"stream closed after {n - left} of {n} bytes")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def read_message(stream: BinaryIO) -> tuple[dict[str, Any], np.ndarray | None]:
    """The next (header, float32 array or None) from ``stream``; :class:`ProtocolError` at its end."""
    n_head, n_payload = _PREFIX.unpack(_read_exact(stream, _PREFIX.size))
    if n_head > MAX_HEADER:
        raise ProtocolError(f"header of {n_head} bytes (at most {MAX_HEADER}): the stream is out of step")
    header = json.loads(_read_exact(stream, n_head).decode("utf-8"))
    if not isinstance(header, dict):
        raise ProtocolError(f"header must be a JSON object, got {type(header).__name__}")
    if not n_payload:
        return header, None
    shape = tuple(int(s) for s in header.get("shape", ()))
    if int(np.prod(shape)) * 4 != n_payload:
        raise ProtocolError(f"payload of {n_payload} bytes does not hold a float32 array of shape {shape}")
    return header, np.frombuffer(_read_exact(stream, n_payload), dtype=np.float32).reshape(shape)
