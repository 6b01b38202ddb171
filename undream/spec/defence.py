"""A defended victim's settings (``defence`` in RUN.yaml, ``--defence`` of ``undream evaluate``).

No heavy imports: the transforms themselves are :mod:`undream.victims.defences`, the wrapper that
applies them in front of any victim :mod:`undream.victims.defended`.

A defence is a chain of input transforms that the victim's frames (sRGB, [0, 1]) pass through, in
order, before the victim sees them:

- ``{jpeg: Q}``: JPEG compression at quality ``Q`` (1–100; Pillow's encoder, 8-bit);
- ``{median: K}``: a K×K median filter (K odd, 3–15);
- ``{gaussian: S}``: Gaussian smoothing of standard deviation ``S`` pixels (0 < S ≤ 10);
- ``{bits: B}``: bit-depth reduction to ``B`` bits per channel (1–8);
- ``{resize_pad: {scale: [LO, HI], pad: P, fill: F}}``: random resize by a factor uniform in
  [LO, HI] onto a canvas ``1 + P`` times the frame's size at a random place, the rest filled with
  grey level ``F`` (defaults: scale [0.9, 1.0], pad 0, fill 0.5; 0.25 ≤ LO ≤ HI ≤ 1 + P, 0 ≤ P ≤ 1).

How an attack differentiates through them (``backward``):

- ``auto``: exact autograd where the transform is differentiable (gaussian, resize_pad), BPDA with
  the identity on the backward pass where it is not (jpeg, median, bits);
- ``bpda``: the identity on the backward pass for every transform that keeps the frame's pixels in
  place (jpeg, median, bits, gaussian); resize_pad, which moves them, is always differentiated exactly;
- ``smooth``: as ``auto``, but with smooth stand-ins instead of the identity (Athalye et al. 2018):
  the median's backward pass is that of a K×K mean filter, jpeg's that of a differentiable JPEG
  approximation (block DCT, cubic rounding; Shin & Song 2017); bits keeps the identity;
- ``exact``: plain autograd through every transform: bits' rounding then passes no gradient and the
  median only its chosen pixel's (the obfuscated gradients a non-adaptive attack meets); jpeg has
  no autograd and is refused.

``adaptive``: True (default): the attack differentiates through the defence as ``backward`` says
and draws the random transforms (EOT); False: the attack ignores the defence and optimises against
the undefended victim. The evaluation always judges the DEFENDED victim. ``draws``: EOT samples of
the random transforms per frame and iteration, the frame's loss their mean (needs resize_pad).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec import _check as c

KINDS = ("jpeg", "median", "gaussian", "bits", "resize_pad")
RANDOM = ("resize_pad",)  # transforms drawn anew per frame and iteration
GEOMETRIC = ("resize_pad",)  # transforms that move pixels (boxes are mapped through them)
BACKWARDS = ("auto", "bpda", "smooth", "exact")
OPTIONS = ("steps", "backward", "adaptive", "draws")
MAX_STEPS = 8
MAX_DRAWS = 64
RESIZE_DEFAULTS = {"scale": (0.9, 1.0), "pad": 0.0, "fill": 0.5}


@dataclass(frozen=True)
class DefenceStep:
    """One transform of the chain. ``kind``: one of :data:`KINDS`. ``value``: jpeg's quality,
    median's kernel (pixels), gaussian's σ (pixels), bits' depth; unused by resize_pad, whose
    ``scale`` (low, high factor), ``pad`` (canvas margin, a fraction of the frame's size) and
    ``fill`` (sRGB grey level in [0, 1]) are its own."""

    kind: str
    value: float = 0.0
    scale: tuple[float, float] = (0.9, 1.0)
    pad: float = 0.0
    fill: float = 0.5

    def __post_init__(self) -> None:
        c.choice("kind", self.kind, KINDS)
        check = {"jpeg": _quality, "median": _kernel, "gaussian": _sigma, "bits": _bits}.get(self.kind)
        if check is not None:
            object.__setattr__(self, "value", check(self.kind, self.value))
        else:
            self._check_resize()

    def _check_resize(self) -> None:
        pad = c.finite("pad", self.pad)
        if not 0.0 <= pad <= 1.0:
            raise c.fail("pad", self.pad, "must be in [0, 1] (a fraction of the frame's size)")
        fill = c.finite("fill", self.fill)
        if not 0.0 <= fill <= 1.0:
            raise c.fail("fill", self.fill, "must be an sRGB grey level in [0, 1]")
        lo, hi = c.vector("scale", self.scale, 2)
        if not 0.25 <= lo <= hi <= 1.0 + pad:
            raise c.fail("scale", list(self.scale), f"must be [low, high] with 0.25 <= low <= high <= 1 + pad "
                         f"({1.0 + pad:g})")
        object.__setattr__(self, "scale", (lo, hi))
        object.__setattr__(self, "pad", pad)
        object.__setattr__(self, "fill", fill)

    @property
    def random(self) -> bool:
        return self.kind in RANDOM

    @property
    def label(self) -> str:
        """A short name: ``jpeg 75``, ``median 3``, ``gaussian 1``, ``bits 4``, ``resize_pad 0.9-1``."""
        if self.kind == "resize_pad":
            return f"resize_pad {self.scale[0]:g}-{self.scale[1]:g}" + (f" pad {self.pad:g}" if self.pad else "")
        return f"{self.kind} {self.value:g}"

    def to_json(self) -> dict[str, Any]:
        """RUN.yaml's form: ``{jpeg: 75}``, ``{resize_pad: {scale: [...], pad: ..., fill: ...}}``."""
        if self.kind == "resize_pad":
            return {"resize_pad": {"scale": list(self.scale), "pad": self.pad, "fill": self.fill}}
        value = self.value
        return {self.kind: int(value) if self.kind in ("jpeg", "median", "bits") else value}

    @classmethod
    def from_json(cls, d: Any) -> "DefenceStep":
        """One step: a mapping of ONE kind to its setting (see the module docstring)."""
        if not isinstance(d, Mapping) or len(d) != 1:
            raise SpecError(f"must be one mapping of a defence to its setting, e.g. {{jpeg: 75}} "
                            f"(defences: {', '.join(KINDS)}), got {d!r}")
        ((kind, setting),) = d.items()
        if kind not in KINDS:
            raise SpecError(f"{kind}: unknown defence; valid are {', '.join(KINDS)}")
        if kind != "resize_pad":
            return cls(kind, setting)
        setting = {} if setting is None else c.mapping(kind, setting)
        with c.at(kind):
            c.no_extra(setting, set(RESIZE_DEFAULTS))
        with c.at(kind):
            return cls(kind, **{**RESIZE_DEFAULTS, **setting})


def _integer(kind: str, value: Any, lo: int, hi: int, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi \
            or value != int(value):
        raise c.fail(kind, value, f"must be {what}, an integer in {lo}..{hi}")
    return float(value)


def _quality(kind: str, value: Any) -> float:
    return _integer(kind, value, 1, 100, "a JPEG quality")


def _bits(kind: str, value: Any) -> float:
    return _integer(kind, value, 1, 8, "a bit depth per channel")


def _kernel(kind: str, value: Any) -> float:
    v = _integer(kind, value, 3, 15, "an odd kernel size in pixels")
    if int(v) % 2 == 0:
        raise c.fail(kind, value, "must be an odd kernel size in pixels, an integer in 3..15")
    return v


def _sigma(kind: str, value: Any) -> float:
    v = c.finite(kind, value)
    if not 0.0 < v <= 10.0:
        raise c.fail(kind, value, "must be a standard deviation in pixels in (0, 10]")
    return v


@dataclass(frozen=True)
class DefenceConfig:
    """A defence in front of the run's victim (see the module docstring): ``steps`` in order,
    ``backward``, ``adaptive``, ``draws``."""

    steps: tuple[DefenceStep, ...]
    backward: str = "auto"
    adaptive: bool = True
    draws: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.steps, (str, bytes, Mapping)) or not isinstance(self.steps, (list, tuple)) \
                or not self.steps:
            raise c.fail("steps", self.steps, "must be a non-empty list of defences such as [{jpeg: 75}]")
        if len(self.steps) > MAX_STEPS:
            raise c.fail("steps", f"{len(self.steps)} defences", f"must hold at most {MAX_STEPS}")
        steps = []
        for i, step in enumerate(self.steps):
            if not isinstance(step, (DefenceStep, Mapping)) or (isinstance(step, Mapping) and len(step) != 1):
                raise c.fail(f"steps[{i}]", step, "must be one mapping of a defence to its setting, e.g. "
                             f"{{jpeg: 75}} (defences: {', '.join(KINDS)})")
            with c.at(f"steps[{i}]"):
                steps.append(step if isinstance(step, DefenceStep) else DefenceStep.from_json(step))
        object.__setattr__(self, "steps", tuple(steps))
        c.choice("backward", self.backward, BACKWARDS)
        if not isinstance(self.adaptive, bool):
            raise c.fail("adaptive", self.adaptive, "must be true (attack through the defence) or false "
                         "(attack the undefended victim)")
        c.integer("draws", self.draws, 1, MAX_DRAWS)
        if self.draws > 1 and not self.random:
            raise c.fail("draws", self.draws, "must be 1 without a random defence (resize_pad): "
                         f"{self.label} draws nothing")
        if self.backward == "exact" and any(s.kind == "jpeg" for s in self.steps):
            raise c.fail("backward", self.backward, "cannot differentiate jpeg exactly (Pillow's codec has "
                         "no gradient); use auto, bpda or smooth")

    @property
    def random(self) -> bool:
        """Whether any step is drawn anew per frame and iteration."""
        return any(s.random for s in self.steps)

    @property
    def label(self) -> str:
        """The chain in short: ``jpeg 75 + median 3``."""
        return " + ".join(s.label for s in self.steps)

    def to_json(self) -> dict[str, Any]:
        return {"steps": [s.to_json() for s in self.steps], "backward": self.backward,
                "adaptive": self.adaptive, "draws": self.draws}

    @classmethod
    def from_json(cls, d: Any) -> "DefenceConfig":
        """``defence`` of RUN.yaml: a list of steps (``[{jpeg: 75}, {median: 3}]``), a mapping of steps
        in order with options beside them (``{jpeg: 75, backward: bpda}``), or the full form
        (``{steps: [...], backward: ..., adaptive: ..., draws: ...}``)."""
        if not isinstance(d, (list, tuple, Mapping)):
            raise c.fail("defence", d, "must be a list of defences such as [{jpeg: 75}, {median: 3}] or a "
                         "mapping such as {jpeg: 75, backward: bpda}")
        with c.at("defence"):
            if isinstance(d, (list, tuple)):
                return cls(tuple(d))
            unknown = [k for k in d if k not in KINDS and k not in OPTIONS]
            if unknown:
                raise SpecError(f"{unknown[0]}: unknown; valid are the defences {', '.join(KINDS)} and the "
                                f"options {', '.join(OPTIONS)}")
            inline = [{k: v} for k, v in d.items() if k in KINDS]
            if inline and "steps" in d:
                raise c.fail("steps", d["steps"], f"is given beside defences named inline "
                             f"({', '.join(next(iter(s)) for s in inline)}); give one or the other")
            steps = d["steps"] if "steps" in d else tuple(inline)
            return cls(steps, **{k: v for k, v in d.items() if k in OPTIONS and k != "steps"})


def typed_defence(value: Any) -> DefenceConfig | None:
    """``value`` (None, a :class:`DefenceConfig` or its RUN.yaml form) as a :class:`DefenceConfig`."""
    if value is None or isinstance(value, DefenceConfig):
        return value
    return DefenceConfig.from_json(value)
