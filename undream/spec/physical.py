"""A run's physical-realisability options (no heavy imports): the objective's regularisers and
print-and-capture EOT.

``regularise`` (:class:`RegulariseConfig`): weights of the terms subtracted from the victim's loss
(the attack maximises ``victim_loss − Σ w_i R_i(T)``; the math is :mod:`undream.attacks.regularise`)
and the palettes the colour terms measure against. ``eot_print`` (:class:`PrintEotConfig`): how much
each iteration's per-frame draw may change the texture's colours, blur it as a print would and add
camera noise to the rendered frame (:mod:`undream.attacks.print_capture`).

Palettes are CSV files of sRGB colours, one ``r,g,b`` line per colour in 0–255 (integers or
decimals); ``#`` starts a comment (to the end of its line) and a first line that is not three numbers (a
header such as ``r,g,b``) is skipped. The colours are read when the config is checked and kept in
the config (``palette_rgb``, ``background_rgb``), so a stored run needs no file: a worker on another
machine reads the same colours from the run's config.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec import _check as c
from undream.spec.io import _text

PALETTES_DIR = Path(__file__).resolve().parents[1] / "data" / "palettes"
BUILTIN_PALETTES = {"printable": PALETTES_DIR / "printable.csv"}  # name → shipped CSV
MAX_PALETTE = 4096  # colours of one palette
MAX_PALETTE_BYTES = 1 << 20
MAX_WEIGHT = 1e6
Colours = tuple[tuple[float, float, float], ...]  # sRGB, 0–255


def palette_path(source: str) -> Path:
    """The CSV a palette ``source`` names: a built-in name (:data:`BUILTIN_PALETTES`) or a path."""
    return BUILTIN_PALETTES.get(source, Path(source))


def read_palette(field: str, source: str) -> Colours:
    """The sRGB colours (0–255) of the palette ``source`` (a built-in name or a CSV path, see the
    module docstring); one :class:`SpecError` line naming ``field``, the file and the line otherwise."""
    path = palette_path(source)
    try:
        text = _text(path, MAX_PALETTE_BYTES)
    except SpecError as err:
        raise SpecError(f"{field}: {err}") from None
    colours = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p.strip() for p in line.replace(";", ",").split(",")]
        values = _numbers(parts)
        if values is None and not colours and not any(ch.isdigit() for ch in line):
            continue  # a header line (r,g,b)
        where = f"{field}: {path} line {number}"
        if values is None or len(values) != 3:
            raise SpecError(f"{where}: expected 3 numbers r,g,b (sRGB, 0-255), got {line[:80]!r}")
        if any(not 0 <= v <= 255 for v in values):
            raise SpecError(f"{where}: values must be sRGB in 0-255, got {line[:80]!r}")
        colours.append((values[0], values[1], values[2]))
        if len(colours) > MAX_PALETTE:
            raise SpecError(f"{field}: {path}: more than {MAX_PALETTE} colours")
    if not colours:
        raise SpecError(f"{field}: {path}: no colours (expected lines of r,g,b in 0-255)")
    return tuple(colours)


def _numbers(parts: list[str]) -> list[float] | None:
    try:
        values = [float(p) for p in parts]
    except ValueError:
        return None
    return values if all(math.isfinite(v) for v in values) else None


def _colours(field: str, value: Any) -> Colours:
    """Colours given inline (a stored config's ``palette_rgb``): a non-empty list of sRGB 0–255 triplets."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)) or not value:
        raise c.fail(field, value, "must be a non-empty list of [r, g, b] sRGB colours in 0-255")
    if len(value) > MAX_PALETTE:
        raise c.fail(field, f"{len(value)} colours", f"must hold at most {MAX_PALETTE} colours")
    out = []
    for i, rgb in enumerate(value):
        v = c.vector(f"{field}[{i}]", rgb, 3)
        if any(not 0 <= x <= 255 for x in v):
            raise c.fail(f"{field}[{i}]", rgb, "must be an sRGB colour in 0-255")
        out.append((v[0], v[1], v[2]))
    return tuple(out)


def _weight(field: str, value: Any) -> float:
    v = c.finite(field, value)
    if not 0 <= v <= MAX_WEIGHT:
        raise c.fail(field, value, f"must be a weight in [0, {MAX_WEIGHT:g}]")
    return v


@dataclass(frozen=True)
class RegulariseConfig:
    """The objective's regularisers (``regularise`` in RUN.yaml); weights ≥ 0, 0 leaves a term out.

    ``tv``: total variation (Thys et al. 2019), smoothness. ``nps``: non-printability score (Sharif
    et al. 2016): distance of each texel to the nearest colour of ``palette`` (default the shipped
    ``printable``, colours of a CMYK printer's gamut, see docs/runs.md). ``camouflage``: distance of
    each texel to the nearest colour of ``background`` (a CSV the user gives, e.g. colours sampled
    from photos of the place; required with ``camouflage`` > 0). ``palette`` and ``background``: a
    built-in name or a CSV path, read when the config is checked into ``palette_rgb`` and
    ``background_rgb`` (sRGB 0–255), which a stored config holds and which win over the files.
    """

    tv: float = 0.0
    nps: float = 0.0
    camouflage: float = 0.0
    palette: str | None = None
    background: str | None = None
    palette_rgb: Colours | None = None
    background_rgb: Colours | None = None

    def __post_init__(self) -> None:
        for name in ("tv", "nps", "camouflage"):
            object.__setattr__(self, name, _weight(name, getattr(self, name)))
        for name in ("palette", "background"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, str) or not value):
                raise c.fail(name, value, "must be a palette name (printable) or a CSV file of r,g,b lines")
        for name, source, needed in (("palette", self.palette or "printable", self.nps > 0 or self.palette),
                                     ("background", self.background, self.background)):
            given = getattr(self, f"{name}_rgb")
            if given is not None:
                object.__setattr__(self, f"{name}_rgb", _colours(f"{name}_rgb", given))
            elif needed:
                object.__setattr__(self, f"{name}_rgb", read_palette(name, source))
        if self.camouflage > 0 and self.background_rgb is None:
            raise c.fail("camouflage", self.camouflage, "needs background: a CSV of the background's colours")

    @property
    def active(self) -> bool:
        """Whether any term has a weight above 0."""
        return self.tv > 0 or self.nps > 0 or self.camouflage > 0

    def to_json(self) -> dict[str, Any]:
        def plain(colours: Colours | None) -> list[list[float]] | None:
            return None if colours is None else [list(rgb) for rgb in colours]

        return {"tv": self.tv, "nps": self.nps, "camouflage": self.camouflage, "palette": self.palette,
                "background": self.background, "palette_rgb": plain(self.palette_rgb),
                "background_rgb": plain(self.background_rgb)}

    @classmethod
    def from_json(cls, d: Any, base_dir: str | Path | None = None) -> "RegulariseConfig":
        """From RUN.yaml's ``regularise`` mapping; relative palette paths against ``base_dir``
        (the run file's folder; the working directory when None)."""
        d = dict(c.mapping("regularise", d))
        with c.at("regularise"):
            c.no_extra(d, set(cls.__dataclass_fields__))
            for name in ("palette", "background"):
                value = d.get(name)
                if isinstance(value, str) and value not in BUILTIN_PALETTES and base_dir is not None \
                        and not Path(value).is_absolute():
                    d[name] = str(Path(base_dir) / value)
            return cls(**d)


# eot_print: field → (largest value, meaning). Each iteration draws, per frame: a brightness offset
# uniform in ±brightness (added, sRGB 0–1), contrast and saturation factors uniform in 1 ± value, a
# gamma exponent exp(uniform ±gamma), a print blur σ uniform in [0, blur] texels and camera noise of
# standard deviation noise (sRGB 0–1) on the rendered frame (undream.attacks.print_capture).
PRINT_EOT_FIELDS = {"brightness": (0.5, "sRGB 0-1 offset"), "contrast": (0.9, "a fraction"),
                    "saturation": (0.9, "a fraction"), "gamma": (1.0, "log of the exponent"),
                    "blur": (16.0, "texels (Gaussian sigma)"), "noise": (0.5, "sRGB 0-1 std")}


@dataclass(frozen=True)
class PrintEotConfig:
    """Print-and-capture EOT (``eot_print`` in RUN.yaml): the largest change each draw may make;
    every field 0 by default (left out). See :data:`PRINT_EOT_FIELDS`."""

    brightness: float = 0.0
    contrast: float = 0.0
    saturation: float = 0.0
    gamma: float = 0.0
    blur: float = 0.0
    noise: float = 0.0

    def __post_init__(self) -> None:
        for name, (most, unit) in PRINT_EOT_FIELDS.items():
            v = c.finite(name, getattr(self, name))
            if not 0 <= v <= most:
                raise c.fail(name, getattr(self, name), f"must be in [0, {most:g}] ({unit})")
            object.__setattr__(self, name, v)

    def to_json(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in PRINT_EOT_FIELDS}

    @classmethod
    def from_json(cls, d: Any) -> "PrintEotConfig":
        d = c.mapping("eot_print", d)
        with c.at("eot_print"):
            c.no_extra(d, set(PRINT_EOT_FIELDS))
            return cls(**d)


def typed(cls: Any, value: Any, **kw: Any) -> Any:
    """``value`` as ``cls`` (a mapping parsed with ``cls.from_json``); None stays None."""
    if value is None or isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise c.fail("regularise" if cls is RegulariseConfig else "eot_print", value, "must be a mapping")
    return cls.from_json(value, **kw)
