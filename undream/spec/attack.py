"""The attack config: which attack, its budget and its knobs, as plain data.

This module imports no torch, so the run config, the store and the scheduler
can hold and validate an :class:`AttackConfig` without it. Turning a config
into a step function is :func:`undream.attacks.make_attack`, which also checks
the name against the registry.

Units: ``eps``, ``step_size`` and ``lr`` are in **0–255 units of the sRGB
texture** (``eps=8`` is the usual 8/255). ``eps >= 255`` leaves only the
[0, 1] box: every texel may take any value.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec.limits import bounded


FRAME_WEIGHTS = ("mean", "unit")  # AttackConfig.frame_weights
STEP_DECAYS = ("none", "cosine")  # AttackConfig.step_decay


def _fail(field: str, value: Any, expected: str) -> SpecError:
    return SpecError(f"attack.{field}: {expected}, got {value!r}")


@dataclass(frozen=True)
class AttackConfig:
    """One attack, chosen by ``name`` among the registered ones.

    - ``name``: ``pgd``, ``apgd``, ``mifgsm``, ``adam`` or any registered name.
    - ``eps``: L∞ budget around the starting texture, 0–255 units; ``>= 255``
      means unbounded within [0, 1].
    - ``steps``: iterations N. APGD's checkpoint schedule is derived from it;
      PGD and MI-FGSM derive their default step size from it.
    - ``step_size``: sign-step size for PGD and MI-FGSM, 0–255 units. None:
      ``2.5·eps/steps`` for PGD (the robustness library's rule), ``eps/steps``
      for MI-FGSM (Dong et al. 2018). APGD's first step η₀ (None: 2·eps, the
      paper's; it halves from there).
    - ``random_start``: start from a random point of the ε ball (visible
      texels only).
    - ``momentum``: MI-FGSM's decay μ.
    - ``lr``: Adam's learning rate, 0–255 units (Adam's first steps move each
      texel by about ``lr``/255).
    - ``rho``: APGD's oscillation threshold ρ (Croce & Hein use 0.75).
    - ``seed``: seeds the random start and the frame minibatches.
    - ``frames_per_step``: frames averaged per iteration; None: all frames.
    - ``frame_weights``: how an iteration's frames' texture gradients are combined. ``mean``: their
      mean (the gradient of the mean loss). ``unit``: each scaled to the frames' mean L2 norm
      first, so that a frame where the texture moves few pixels (a back-lit view at night, a far
      camera) steers the step as much as a sunlit one (docs/runs.md, "Lamps at night").
    - ``step_decay``: PGD's and MI-FGSM's step size over the iterations. ``none``: ``step_size``
      throughout. ``cosine``: ``step_size·(1 + cos(π·k/steps))/2`` at iteration k, from
      ``step_size`` down to nearly 0, so that a run on minibatches of frames, whose gradient changes
      with every draw, settles on a texture instead of ending wherever its last fixed step left it
      (docs/runs.md, "Lamps at night").
    - ``grad_blur``: σ, in texels, of a Gaussian that smooths each iteration's texture gradient
      before the attack uses it (0: off). The translation-invariant attack of Dong et al. 2019
      moved onto the texture: each step moves a texel with its neighbours, so the texture changes
      in patches a far or blurred view still resolves (docs/runs.md, "Smoothed gradients").
    """

    name: str = "pgd"
    eps: float = 8.0
    steps: int = 100
    step_size: float | None = None
    random_start: bool = False
    momentum: float = 1.0
    lr: float = 2.0
    rho: float = 0.75
    seed: int = 0
    frames_per_step: int | None = None
    frame_weights: str = "mean"
    step_decay: str = "none"
    grad_blur: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise _fail("name", self.name, "must be a non-empty attack name")
        optional = ("step_size", "frames_per_step")  # None: derived (see above)
        checked = {key: None if key in optional and getattr(self, key) is None
                   else bounded(f"attack.{key}", getattr(self, key))
                   for key in ("eps", "steps", "step_size", "momentum", "lr", "rho", "seed", "frames_per_step",
                               "grad_blur")}
        if not isinstance(self.random_start, bool):
            raise _fail("random_start", self.random_start, "must be true or false")
        if self.frame_weights not in FRAME_WEIGHTS:
            raise _fail("frame_weights", self.frame_weights, f"must be one of {', '.join(FRAME_WEIGHTS)}")
        if self.step_decay not in STEP_DECAYS:
            raise _fail("step_decay", self.step_decay, f"must be one of {', '.join(STEP_DECAYS)}")
        if self.step_decay != "none" and self.name in ("apgd", "adam"):
            raise _fail("step_decay", self.step_decay, f"{self.name} sets its own step sizes; step_decay is "
                        "for pgd and mifgsm (leave it none)")
        for key, value in checked.items():
            object.__setattr__(self, key, value)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "AttackConfig":
        """Build from a JSON/YAML mapping; unknown keys are an error."""
        if not isinstance(data, Mapping):
            raise SpecError(f"attack: must be a mapping of fields, got {data!r}")
        valid = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(valid))
        if unknown:
            raise SpecError(f"attack: unknown field(s) {', '.join(map(str, unknown))}; "
                            f"valid fields are {', '.join(valid)}")
        return cls(**dict(data))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able fields; ``from_dict(to_dict())`` is the identity."""
        return dataclasses.asdict(self)
