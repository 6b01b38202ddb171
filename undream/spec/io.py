"""Reading and writing the canonical ``sequence.json``."""
from __future__ import annotations

import json
from pathlib import Path

from undream.errors import SpecError
from undream.spec.model import Sequence


def load_sequence(path: str | Path) -> Sequence:
    """Parse a canonical ``sequence.json``; errors name the file and the field."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise SpecError(f"{path}: file not found") from None
    except json.JSONDecodeError as err:
        raise SpecError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    try:
        return Sequence.from_json(data)
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None


def save_sequence(seq: Sequence, path: str | Path) -> None:
    """Write ``seq`` as canonical JSON (the exact inverse of :func:`load_sequence`)."""
    Path(path).write_text(json.dumps(seq.to_json(), indent=1) + "\n")
