"""Every bound on undream's inputs, stated once.

The spec, the run config, the attack block and sweep files check their
numbers against :data:`BOUNDS` (through :func:`bounded`), and every input file
is read under :data:`FILE_LIMITS` (:mod:`undream.spec.io`), so a refusal names
the field, the value and the valid range in one place. ``docs/safety.md``
lists the same table.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from undream.errors import SpecError


@dataclass(frozen=True)
class Bound:
    """``lo ≤ value ≤ hi`` (``lo < value`` where ``lo_open``); ``integer``: whole numbers only."""

    lo: float
    hi: float
    integer: bool = False
    lo_open: bool = False
    unit: str = ""

    def describe(self, name: str) -> str:
        lo = f"{_number(self.lo)} {'<' if self.lo_open else '≤'} "
        return f"{lo}{name} ≤ {_number(self.hi)}" + (f" ({self.unit})" if self.unit else "")


def _number(x: float) -> str:
    """A bound as a user types it: whole numbers in full (2147483647, not 2.14748e+09)."""
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


MAX_FRAMES = 10_000  # frames of one sequence
MAX_SWEEP_RUNS = 10_000  # runs of one sweep grid, unless `undream sweep --max-runs` raises it

# field (as named in messages) → its bound
BOUNDS: dict[str, Bound] = {
    "frames": Bound(1, MAX_FRAMES, integer=True),
    "attack.eps": Bound(0, 255, lo_open=True, unit="0-255 units of the sRGB texture"),
    "attack.steps": Bound(1, 100_000, integer=True),
    "attack.step_size": Bound(0, 255, lo_open=True, unit="0-255 units"),
    "attack.lr": Bound(0, 255, lo_open=True, unit="0-255 units"),
    "attack.momentum": Bound(0, 1000),
    "attack.rho": Bound(0, 1, lo_open=True),
    "attack.seed": Bound(0, 2**31 - 1, integer=True),
    "attack.frames_per_step": Bound(1, MAX_FRAMES, integer=True),
    "attack.grad_blur": Bound(0, 64, unit="texels, the Gaussian's σ; 0: off"),
    "sim_spp": Bound(1, 65_536, integer=True),
    "grad_spp": Bound(1, 65_536, integer=True),
    "eval_spp": Bound(1, 65_536, integer=True),
    "seed": Bound(0, 2**31 - 1, integer=True),
}

# What any input file may hold (YAML and JSON alike), checked while it is read.
FILE_LIMITS = {
    "yaml_bytes": 1 << 20,  # a hand-written spec, run config, sweep or settings file
    "json_bytes": 64 << 20,  # a canonical sequence.json or an Unreal export of up to MAX_FRAMES frames
    "depth": 64,  # nested mappings and lists
    "nodes": 1_000_000,  # values after every alias is expanded
    "digits": 100,  # digits of one number
}


def bounded(field: str, value: Any, key: str | None = None) -> Any:
    """``value`` checked against ``BOUNDS[key or field]``: an ``int`` for integer bounds, else a
    ``float``; :class:`SpecError` naming ``field``, the value and the valid range otherwise."""
    bound = BOUNDS[key or field]
    name = field.rsplit(".", 1)[-1]
    valid = f"valid: {bound.describe(name)}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(f"{field}: {value!r} is not a number ({valid})")
    if bound.integer and not isinstance(value, int):
        raise SpecError(f"{field}: {value!r} is not a whole number ({valid})")
    if not math.isfinite(value) or value > bound.hi or value < bound.lo or (bound.lo_open and value == bound.lo):
        shown = value if not isinstance(value, int) or abs(value) < 10**30 else \
            f"a number of about {int(value.bit_length() * math.log10(2)) + 1} digits"
        raise SpecError(f"{field}: {shown} is out of range ({valid})")
    return value if bound.integer else float(value)
